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
