//! What a report normalises with: the expert and random mean return of each task, read from the
//! data's card (`dataset.json`), or from an archived run's `normalisation.json` (the results
//! registry), which records the card's numbers the run was scored with. One module, used by the
//! report and by the registry.

use crate::ReproError;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// The file of an archived run that holds the returns it was scored with.
pub const NORMALISATION_JSON: &str = "normalisation.json";

/// Expert and random mean return per task index, from a dataset card.
#[derive(Debug, Clone, Default)]
pub struct Baselines {
    pub expert: BTreeMap<usize, f64>,
    pub random: BTreeMap<usize, f64>,
}

pub fn baselines(data_dir: &Path) -> Result<Baselines, ReproError> {
    let card = pdt_data::native::read_card(data_dir)
        .map_err(|e| ReproError::Invalid(e.to_string()))?
        .ok_or_else(|| ReproError::Invalid(format!("{}: no dataset card", data_dir.display())))?;
    let mut b = Baselines::default();
    for t in &card.tasks {
        for f in &t.files {
            match f.mode.as_str() {
                "expert" => {
                    b.expert.insert(t.index, f.returns.mean);
                }
                "random" => {
                    b.random.insert(t.index, f.returns.mean);
                }
                _ => {}
            }
        }
    }
    Ok(b)
}

/// What a run on a task suite is normalised with: the suite's own per-task `expert_return` and
/// `random_return` (`EnvFamily::reference_returns`), as the run trained on it (its copy in
/// `run_dir`, else the file `env`). `None` when `env` is no suite (a built-in family's scores come
/// from its dataset card, [`baselines`]); `Err` says why a suite's scores are not normalised (it
/// declares no task's returns, or cannot be read): never a number made up in their place.
pub fn suite_baselines(env: &str, run_dir: &Path) -> Option<Result<Baselines, String>> {
    if !pdt_envs::suite::is_suite_path(env) {
        return None;
    }
    let copy = pdt_rundir::RunDir::at(run_dir).suite_path();
    let family = match pdt_envs::family_of_run(env, &copy) {
        Ok(f) => f,
        Err(e) => return Some(Err(format!("not normalised: {e}"))),
    };
    let mut b = Baselines::default();
    for t in 0..family.num_tasks() {
        if let Some((expert, random)) = family.reference_returns(t) {
            b.expert.insert(t, expert);
            b.random.insert(t, random);
        }
    }
    Some(match b.expert.is_empty() {
        true => Err(format!(
            "not normalised: the suite {} declares no task's expert_return and random_return",
            family.name()
        )),
        false => Ok(b),
    })
}

/// One task's returns in `normalisation.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskBaseline {
    pub task_index: usize,
    pub expert_return: f64,
    pub random_return: f64,
}

/// `normalisation.json`: the dataset card's mean returns the report normalises with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Normalisation {
    /// The data directory's name (`<env>[-e<episodes>]`) whose `dataset.json` they come from.
    pub dataset: String,
    pub tasks: Vec<TaskBaseline>,
}

impl Normalisation {
    pub(crate) fn from_baselines(dataset: String, b: &Baselines) -> Self {
        let tasks = b
            .expert
            .iter()
            .filter_map(|(t, e)| {
                Some(TaskBaseline {
                    task_index: *t,
                    expert_return: *e,
                    random_return: *b.random.get(t)?,
                })
            })
            .collect();
        Self { dataset, tasks }
    }

    pub fn baselines(&self) -> Baselines {
        let mut b = Baselines::default();
        for t in &self.tasks {
            b.expert.insert(t.task_index, t.expert_return);
            b.random.insert(t.task_index, t.random_return);
        }
        b
    }
}

/// The baselines an archived run was scored with (its `normalisation.json`), if it has them.
pub fn archived_baselines(run_dir: &Path) -> Option<Baselines> {
    pdt_rundir::read_json::<Normalisation>(&run_dir.join(NORMALISATION_JSON))
        .ok()
        .map(|n| n.baselines())
}

#[cfg(test)]
mod tests {
    use super::*;

    const SUITE: &str = r#"
name = "toy_norm"
obs_dim = 1
act_dim = 1
action_bound = 1.0
max_ep_len = 5
rtg_scale = 1
target_return = 1.0
prompt_length = 2
[[tasks]]
name = "a"
expert_return = 9.0
random_return = 1.0
[[tasks]]
name = "b"
[splits.main]
train = ["b"]
test = ["a"]
"#;

    /// A suite's runs are normalised with the returns its tasks declare, only those; a suite
    /// declaring none is "not normalised", never given a number; a built-in family is not a
    /// suite's business.
    #[test]
    fn a_suites_declared_returns_normalise_its_runs_and_none_declared_is_said() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("suite.toml");
        std::fs::write(&path, SUITE).unwrap();
        let no_run = tmp.path().join("no-run");
        let b = suite_baselines(path.to_str().unwrap(), &no_run).unwrap().unwrap();
        assert_eq!(b.expert.into_iter().collect::<Vec<_>>(), [(0, 9.0)]);
        assert_eq!(b.random.into_iter().collect::<Vec<_>>(), [(0, 1.0)]);

        let bare = SUITE.replace("expert_return = 9.0\nrandom_return = 1.0\n", "");
        std::fs::write(&path, bare).unwrap();
        let why = suite_baselines(path.to_str().unwrap(), &no_run).unwrap().unwrap_err();
        assert!(why.starts_with("not normalised") && why.contains("toy_norm"), "{why}");

        assert!(suite_baselines("point_robot", &no_run).is_none());
    }
}
