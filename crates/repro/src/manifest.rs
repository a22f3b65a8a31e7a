//! Experiment manifests (`experiments/*.toml`): one per paper artifact, each a list of cells (an
//! environment, a method and its variant) with the paper's value for the cell, and budgets (how
//! many iterations and seeds, and the reduced settings of the `cpu` and `smoke` budgets).
//!
//! The committed manifests are compiled in ([`builtin`]), so `promptdt reproduce fig2` works from
//! any directory; a path to another manifest file works too. A manifest file may name a user's task
//! suites (`[suites.<name>]`, [`crate::suites`]) as its cells' environments.

use crate::suites::SuiteRef;
use crate::ReproError;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The committed manifests, in the order `--list` shows them.
pub const BUILTIN: &[(&str, &str)] = &[
    ("fig2", include_str!("../../../experiments/fig2.toml")),
    ("table1", include_str!("../../../experiments/table1.toml")),
    ("fig3", include_str!("../../../experiments/fig3.toml")),
    ("fig4", include_str!("../../../experiments/fig4.toml")),
    (
        "appendix_prompt_length_mt_bc",
        include_str!("../../../experiments/appendix_prompt_length_mt_bc.toml"),
    ),
    ("appendix_finetune_mt_bc", include_str!("../../../experiments/appendix_finetune_mt_bc.toml")),
    ("appendix_finetune_macaw", include_str!("../../../experiments/appendix_finetune_macaw.toml")),
    ("prompt_control", include_str!("../../../experiments/prompt_control.toml")),
];

/// How the report lays an experiment out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layout {
    /// Learning curves per environment (a panel per environment), like Figure 2.
    Curves,
    /// A table of final returns: rows x columns, like Table 1.
    Table,
}

/// One experiment.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub name: String,
    pub title: String,
    /// What the paper shows and what the experiment checks.
    pub description: String,
    pub layout: Layout,
    /// The paper's claims this experiment tests, each checked by the report (see [`Claim`]).
    #[serde(default)]
    pub claims: Vec<Claim>,
    pub budgets: BTreeMap<String, Budget>,
    pub cells: Vec<Cell>,
    /// The reference release's expert return per task of an environment (see
    /// [`ReferenceExperts`]), keyed by environment: what normalises the paper's values.
    #[serde(default)]
    pub reference_experts: BTreeMap<String, ReferenceExperts>,
    /// A user's task suites the cells may name as their `env` (`[suites.<name>]`): their paths
    /// taken from the manifest file's directory once read ([`Manifest::load`]).
    #[serde(default)]
    pub suites: BTreeMap<String, SuiteRef>,
}

/// The families the reference release has expert prompt files for (`official-prompts/`).
pub const REFERENCE_ENVS: [&str; 2] = ["cheetah_dir", "cheetah_vel"];

/// `[reference_experts.<env>]`: the reference release's expert returns, committed as numbers so a
/// report is complete without the release's files. Generated from the files (`cargo run -p
/// pdt-repro --example reference_experts`), never typed by hand; `tests/it/reference_experts.rs`
/// recomputes them when the files are present.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferenceExperts {
    /// The release's files the numbers come from and how they were computed.
    pub source: String,
    /// Entry i: task i's expert return (every task of the family, in order).
    pub returns: Vec<f64>,
}

/// A statement of the paper the report checks on the measured numbers.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Claim {
    pub text: String,
    pub kind: ClaimKind,
    /// Cell ids (see [`Cell::id`]) the claim compares, within one environment: for `better`,
    /// `a` and `b`; for `insensitive` and `ordered`, all of `cells`.
    #[serde(default)]
    pub a: Option<String>,
    #[serde(default)]
    pub b: Option<String>,
    #[serde(default)]
    pub cells: Vec<String>,
    /// `insensitive`: the largest spread of normalised scores still called insensitive.
    #[serde(default)]
    pub max_spread: Option<f64>,
    /// `better`: how many normalised points `a` must lead `b` by for the claim to hold (default
    /// 10, the band the manifests call "similar"). A lead or a lag inside it reads "too close to
    /// call": with one or two seeds a few points are noise, not evidence.
    #[serde(default)]
    pub min_margin: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClaimKind {
    /// Cell `a` scores higher than cell `b` by more than `min_margin` (normalised, mean over seeds).
    Better,
    /// The cells' normalised scores lie within `max_spread` of each other.
    Insensitive,
    /// The cells score in the order listed, best first.
    Ordered,
}

/// A budget: the settings every run of the experiment gets, then `rules` that change them for
/// some environments or methods (applied in order; later rules win).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Budget {
    /// What the budget is and how long it takes, in words (shown by `--list`).
    pub note: String,
    /// Wall time of the whole experiment at this budget on the machine named in `note`, hours.
    #[serde(default)]
    pub hours: Option<f64>,
    #[serde(flatten)]
    pub settings: Settings,
    #[serde(default)]
    pub rules: Vec<Rule>,
}

/// Settings of a budget or a rule; `None` keeps what came before (in the end, the reference code's
/// default, as in `configs/`).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings {
    pub seeds: Option<u32>,
    pub iterations: Option<u64>,
    pub steps_per_iteration: Option<u64>,
    pub batch_size_per_task: Option<usize>,
    pub eval_episodes: Option<usize>,
    /// Variants: `promptdt eval --repeats N`, the evaluation repeated over N independent prompt
    /// draws and reset seeds (evaluation noise, reported apart from seed noise). Default 1.
    pub eval_repeats: Option<usize>,
    pub test_eval_interval: Option<u64>,
    pub train_eval_interval: Option<u64>,
    pub save_interval: Option<u64>,
    /// Resume points between checkpoints (`train.resume_interval`); not part of a run's identity.
    pub resume_interval: Option<u64>,
    /// Episodes per task and mode in the collected datasets (default: `collect`'s 100).
    pub data_episodes: Option<usize>,
    /// Episodes per task in each collected prompt set (default: `collect`'s 5).
    pub prompt_set_episodes: Option<usize>,
    /// MT-BC-Finetune's fine-tuning batch and steps, overriding the cells' (the smoke budget
    /// shrinks them).
    pub finetune_batch: Option<usize>,
    pub finetune_steps: Option<u64>,
    /// The optimiser's peak learning rate and linear warm-up (`[optim]`; default the reference's
    /// 1e-4 over 10000 steps): a short budget of a few hundred steps would otherwise end its
    /// warm-up at a few percent of the peak rate (a user's experiment sets them; the paper's keep
    /// the reference's).
    pub learning_rate: Option<f64>,
    pub warmup_steps: Option<u64>,
    /// MACAW cells: the preset (`official` or `promptdt`, default `promptdt`: the paper's table),
    /// then its width, its inner and outer batch size and its buffer stride (the smaller budgets
    /// shrink them).
    pub macaw_preset: Option<pdt_rundir::config::macaw::Preset>,
    pub macaw_width: Option<usize>,
    pub macaw_batch: Option<usize>,
    pub macaw_buffer_skip: Option<usize>,
    /// `false`: the matching cells are not run at this budget (the report says so).
    pub run: Option<bool>,
}

impl Settings {
    fn apply(&mut self, o: &Settings) {
        macro_rules! take {
            ($($f:ident),*) => { $( if o.$f.is_some() { self.$f = o.$f; } )* };
        }
        take!(
            seeds,
            iterations,
            steps_per_iteration,
            batch_size_per_task,
            eval_episodes,
            eval_repeats,
            test_eval_interval,
            train_eval_interval,
            save_interval,
            resume_interval,
            data_episodes,
            prompt_set_episodes,
            finetune_batch,
            learning_rate,
            warmup_steps,
            macaw_preset,
            macaw_width,
            macaw_batch,
            macaw_buffer_skip,
            finetune_steps,
            run
        );
    }
}

/// Changes settings for the cells that match (every listed field must match; an empty list
/// matches everything).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rule {
    #[serde(default)]
    pub envs: Vec<String>,
    #[serde(default)]
    pub methods: Vec<String>,
    /// Cell ids.
    #[serde(default)]
    pub cells: Vec<String>,
    #[serde(flatten)]
    pub settings: Settings,
}

impl Rule {
    fn matches(&self, cell: &Cell) -> bool {
        (self.envs.is_empty() || self.envs.contains(&cell.env))
            && (self.methods.is_empty() || self.methods.contains(&cell.method))
            && (self.cells.is_empty() || self.cells.contains(&cell.id()))
    }
}

/// One cell of the paper's artifact: an environment, a method, its variant, and the paper's value.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Cell {
    pub env: String,
    /// Task split (`default`, or `ood` for Ant-Dir's out-of-distribution split).
    #[serde(default)]
    pub split: Option<String>,
    pub method: String,
    /// Prompt: J episodes x H steps (default: the environment's preset, 1 x 5).
    #[serde(default)]
    pub prompt: Option<[usize; 2]>,
    /// Training data D and training prompts P (default `expert`).
    #[serde(default)]
    pub dataset: Option<String>,
    /// Prompts given at test time (default: the training prompts' quality).
    #[serde(default)]
    pub test_prompt: Option<String>,
    /// Where training cuts prompt segments (`sampler.prompt_position`): `tail` (default, the
    /// reference's) or `random` (the paper's Algorithm 2).
    #[serde(default)]
    pub prompt_position: Option<String>,
    /// MT-BC-Finetune: segments per fine-tuning batch and gradient steps per test task.
    #[serde(default)]
    pub finetune_batch: Option<usize>,
    #[serde(default)]
    pub finetune_steps: Option<u64>,
    /// Row and column of a table layout; the legend name of a curves layout (`row`).
    #[serde(default)]
    pub row: Option<String>,
    #[serde(default)]
    pub column: Option<String>,
    /// The paper's value: final average return on the test tasks.
    #[serde(default)]
    pub paper: Option<f64>,
    #[serde(default)]
    pub paper_std: Option<f64>,
    /// Where `paper` comes from ("Table 1", "Fig. 2, read off the plot, approximate").
    #[serde(default)]
    pub paper_source: Option<String>,
    /// Set while the method or environment does not exist in promptdt yet (MACAW, Meta-World,
    /// Dial): the cell is listed in the report with its paper value and this reason, not run.
    #[serde(default)]
    pub pending: Option<String>,
    /// An evaluation variant of a trained cell (docs/reproduce.md, "Variants"): its name, and the
    /// table merged into the base cell's runs' `[eval]` configuration. The base cell is the cell
    /// with the same fields but no `variant` (its id is this id before the `@`); it is not trained
    /// again: each of its finished runs (same seeds) is evaluated with the merged configuration.
    #[serde(default)]
    pub variant: Option<String>,
    #[serde(default)]
    pub eval: Option<toml::Table>,
}

/// What separates a variant's name from its base cell's id in its id.
pub const VARIANT_SEP: char = '@';

impl Cell {
    /// The cell's identity, also the relative path of its runs: `env[-split]/method[-variant]`.
    /// Cells of different experiments with the same id and budget share their runs.
    pub fn id(&self) -> String {
        let mut env = self.env.clone();
        if let Some(s) = self.split.as_deref().filter(|s| *s != "default") {
            env.push('-');
            env.push_str(s);
        }
        let mut m = self.method.clone();
        if let Some([j, h]) = self.prompt {
            m.push_str(&format!("-k{j}x{h}"));
        }
        let d = self.dataset.as_deref().unwrap_or("expert");
        let p = self.test_prompt.as_deref().unwrap_or(d);
        if d != "expert" || p != "expert" {
            m.push_str(&format!("-d{d}-p{p}"));
        }
        if self.prompt_position.as_deref().is_some_and(|p| p != "tail") {
            m.push_str(&format!("-pos{}", self.prompt_position.as_deref().unwrap_or_default()));
        }
        if self.finetune_batch.is_some() || self.finetune_steps.is_some() {
            m.push_str(&format!(
                "-ft{}x{}",
                self.finetune_batch.map_or("def".into(), |b| b.to_string()),
                self.finetune_steps.map_or("def".into(), |s| s.to_string())
            ));
        }
        match &self.variant {
            Some(v) => format!("{env}/{m}{VARIANT_SEP}{v}"),
            None => format!("{env}/{m}"),
        }
    }

    /// The id of the cell a variant evaluates (`None` for a trained cell).
    pub fn base_id(&self) -> Option<String> {
        self.variant.as_ref()?;
        Some(Cell { variant: None, ..self.clone() }.id())
    }

    /// Legend or row name.
    pub fn label(&self) -> String {
        self.row.clone().unwrap_or_else(|| self.method.clone())
    }
}

impl Manifest {
    /// A committed manifest by name, or a manifest file.
    pub fn load(name_or_path: &str) -> Result<Self, ReproError> {
        if let Some((_, text)) = BUILTIN.iter().find(|(n, _)| *n == name_or_path) {
            return Self::parse(text, name_or_path);
        }
        let path = Path::new(name_or_path);
        if path.is_file() {
            let text = pdt_base::fs::read_text_limited(path, pdt_base::fs::MAX_TEXT_BYTES)
                .map_err(|e| ReproError::Io { path: path.to_path_buf(), source: e })?;
            // A suite's paths are the manifest's neighbours wherever `reproduce` runs from.
            let dir = std::path::absolute(path)
                .map_err(|e| ReproError::Io { path: path.to_path_buf(), source: e })?;
            let base = dir.parent().unwrap_or(Path::new("/")).to_path_buf();
            return Self::parse_in(&text, name_or_path, &base);
        }
        Err(ReproError::UnknownExperiment {
            name: name_or_path.to_string(),
            known: BUILTIN.iter().map(|(n, _)| (*n).to_string()).collect(),
        })
    }

    /// A manifest's text; its suites' relative paths are taken from the working directory.
    pub fn parse(text: &str, origin: &str) -> Result<Self, ReproError> {
        let cwd = std::env::current_dir()
            .map_err(|e| ReproError::Io { path: PathBuf::from("."), source: e })?;
        Self::parse_in(text, origin, &cwd)
    }

    /// A manifest's text whose suites' relative paths are taken from `base` (the manifest file's
    /// directory).
    pub fn parse_in(text: &str, origin: &str, base: &Path) -> Result<Self, ReproError> {
        let mut m: Manifest = toml::from_str(text)
            .map_err(|e| ReproError::Manifest { origin: origin.into(), message: e.to_string() })?;
        for s in m.suites.values_mut() {
            *s = s.resolved(base);
        }
        m.check(origin)?;
        Ok(m)
    }

    /// The family name a cell's `env` stands for: a suite's file path for a suite of
    /// `[suites]`, the name itself for a built-in family.
    pub fn family_name(&self, env: &str) -> String {
        self.suites.get(env).map_or_else(|| env.to_string(), SuiteRef::family_name)
    }

    /// The environment family a cell's `env` names (a suite read from its file).
    pub fn family(&self, env: &str) -> Result<Box<dyn pdt_envs::EnvFamily>, pdt_envs::EnvError> {
        pdt_envs::family(&self.family_name(env))
    }

    fn check(&self, origin: &str) -> Result<(), ReproError> {
        let bad = |message: String| Err(ReproError::Manifest { origin: origin.into(), message });
        if self.cells.is_empty() {
            return bad("no cells".into());
        }
        let mut ids = std::collections::HashSet::new();
        for c in &self.cells {
            if !ids.insert(c.id()) {
                return bad(format!("cell {} appears twice", c.id()));
            }
            if let Some(p) =
                c.prompt_position.as_deref().filter(|p| !["tail", "random"].contains(p))
            {
                return bad(format!("cell {}: prompt_position {p:?}: tail or random", c.id()));
            }
            if let Err(why) = self.check_variant(c) {
                return bad(format!("cell {}: {why}", c.id()));
            }
            if c.pending.is_none() {
                if let Err(e) = self.family(&c.env) {
                    // A suite's own error names its file and field; a name is either a suite of
                    // `[suites]` or a built-in family.
                    return bad(match self.suites.contains_key(&c.env) {
                        true => format!("cell {}: suites.{}: {e}", c.id(), c.env),
                        false => format!(
                            "cell {}: unknown environment {:?} (a built-in family, or a suite \
                             named in [suites]: {})",
                            c.id(),
                            c.env,
                            self.suites.keys().cloned().collect::<Vec<_>>().join(", ")
                        ),
                    });
                }
                if c.method.parse::<pdt_rundir::config::Method>().is_err() {
                    return bad(format!("cell {}: unknown method {:?}", c.id(), c.method));
                }
            }
        }
        for (name, b) in &self.budgets {
            for r in &b.rules {
                if let Some(c) = r.cells.iter().find(|c| !ids.contains(*c)) {
                    return bad(format!("budget {name}: rule names unknown cell {c}"));
                }
            }
            // Counts where 0 means nothing: no seeds plans no run (an empty report that reads as
            // a success), no episodes collects no data. The training settings are validated with
            // each run's configuration.
            for s in std::iter::once(&b.settings).chain(b.rules.iter().map(|r| &r.settings)) {
                let zero = [
                    ("seeds", s.seeds.map(u64::from)),
                    ("eval_repeats", s.eval_repeats.map(|v| v as u64)),
                    ("data_episodes", s.data_episodes.map(|v| v as u64)),
                    ("prompt_set_episodes", s.prompt_set_episodes.map(|v| v as u64)),
                ];
                if let Some((key, _)) = zero.iter().find(|(_, v)| *v == Some(0)) {
                    return bad(format!("budget {name}: {key} must be at least 1, got 0"));
                }
            }
        }
        for claim in &self.claims {
            let named = claim.a.iter().chain(claim.b.iter()).chain(claim.cells.iter());
            for c in named {
                if !ids.contains(c) {
                    return bad(format!("claim {:?} names unknown cell {c}", claim.text));
                }
            }
        }
        for name in self.suites.keys() {
            if let Err(why) = crate::suites::check_name(name) {
                return bad(why);
            }
        }
        for (env, r) in &self.reference_experts {
            let at = format!("reference_experts.{env}");
            let Ok(family) = pdt_envs::family(env) else {
                return bad(format!("{at}: unknown environment {env:?}"));
            };
            if r.returns.len() != family.num_tasks() {
                return bad(format!(
                    "{at}.returns: {} values, but {env} has {} tasks",
                    r.returns.len(),
                    family.num_tasks()
                ));
            }
            if let Some(i) = r.returns.iter().position(|x| !x.is_finite() || x.abs() > 1e9) {
                return bad(format!("{at}.returns[{i}] = {}: not a return", r.returns[i]));
            }
            if r.source.trim().is_empty() {
                return bad(format!("{at}.source: empty (name the files the numbers come from)"));
            }
        }
        if !self.budgets.contains_key("smoke") {
            return bad("every experiment needs a smoke budget (CI runs it)".into());
        }
        Ok(())
    }

    /// A variant's base cell, by [`Cell::base_id`]; `Err` names it when it is not in the manifest.
    pub fn base_of(&self, cell: &Cell) -> Result<Option<(usize, &Cell)>, String> {
        let Some(base) = cell.base_id() else { return Ok(None) };
        match self.cells.iter().enumerate().find(|(_, c)| c.id() == base) {
            Some(found) => Ok(Some(found)),
            None => Err(format!(
                "its base cell {base} (the same cell without `variant`) is not in the manifest"
            )),
        }
    }

    /// A variant names a base cell of this manifest and an `[eval]` table that reads as one; a
    /// trained cell has no `eval` table (the override belongs to a variant).
    fn check_variant(&self, c: &Cell) -> Result<(), String> {
        let Some(name) = &c.variant else {
            return match c.eval {
                Some(_) => {
                    Err("`eval` overrides the evaluation of a variant: give it a `variant` \
                                name (docs/reproduce.md, \"Variants\")"
                        .into())
                }
                None => Ok(()),
            };
        };
        let bad_name = |ch: char| !(ch.is_ascii_alphanumeric() || ch == '-' || ch == '_');
        if name.is_empty() || name.contains(bad_name) {
            return Err(format!("variant {name:?}: use letters, digits, `-` and `_`"));
        }
        let Some(eval) = &c.eval else {
            return Err("a variant needs an `eval` table (what its evaluation changes)".into());
        };
        let Some((_, base)) = self.base_of(c)? else { return Ok(()) };
        if c.pending.is_some() {
            // Its override may name what is not built yet (`[eval.adapt]` before it lands).
            return Ok(());
        }
        if let Some(why) = &base.pending {
            return Err(format!("its base cell {} is pending ({why})", base.id()));
        }
        // The keys are checked now, against a default configuration (a typo fails here, not after
        // hours of training); the values again with each run's own configuration.
        crate::variant_spec::with_eval(&pdt_rundir::config::TrainConfig::default(), eval)
            .map(|_| ())
    }

    /// The settings of `cell` at `budget`: the budget's, then every matching rule in order.
    pub fn settings(&self, budget: &str, cell: &Cell) -> Result<Settings, ReproError> {
        let b = self.budget(budget)?;
        let mut s = b.settings.clone();
        for r in b.rules.iter().filter(|r| r.matches(cell)) {
            s.apply(&r.settings);
        }
        Ok(s)
    }

    /// The reference's expert return of each of `tasks` of `env`, from `[reference_experts]`.
    pub fn reference_expert_returns(&self, env: &str, tasks: &[usize]) -> Option<Vec<f64>> {
        let r = self.reference_experts.get(env)?;
        tasks.iter().map(|t| r.returns.get(*t).copied()).collect()
    }

    pub fn budget(&self, budget: &str) -> Result<&Budget, ReproError> {
        self.budgets.get(budget).ok_or_else(|| ReproError::UnknownBudget {
            experiment: self.name.clone(),
            budget: budget.into(),
            known: self.budgets.keys().cloned().collect(),
        })
    }
}

/// Task `t`'s expert return as the reference release's prompt file gives it: the mean episode
/// return of `{dir}/{env}-{t}-prompt-expert.pkl` (rewards summed in f64), the figure
/// `[reference_experts]` commits and `--reference DIR` recomputes.
pub fn reference_expert_return(dir: &Path, env: &str, t: usize) -> Result<f64, ReproError> {
    inspect_prompt_file(dir, env, t).map(|r| r.return_mean)
}

fn inspect_prompt_file(
    dir: &Path,
    env: &str,
    t: usize,
) -> Result<pdt_data::inspect::FileReport, ReproError> {
    let path = dir.join(format!("{env}-{t}-prompt-expert.pkl"));
    pdt_data::inspect::inspect_file(&path)
        .map_err(|e| ReproError::Invalid(format!("{}: {e}", path.display())))
}

/// The `[reference_experts.<env>]` tables of `envs`, from the release's `official-prompts/` in
/// `dir`, as the manifests commit them (between the `# BEGIN reference_experts` and
/// `# END reference_experts` lines).
pub fn render_reference_experts(dir: &Path, envs: &[&str]) -> Result<String, ReproError> {
    let mut out = String::from(
        "# BEGIN reference_experts: generated from the reference release's official-prompts/ by\n\
         # `cargo run --release -p pdt-repro --example reference_experts -- DIR`; do not edit by hand.\n\
         # The report normalises the paper's values with them (docs/reproduce.md).\n",
    );
    for env in envs {
        let n = pdt_envs::family(env).map_err(|e| ReproError::Invalid(e.to_string()))?.num_tasks();
        let mut shapes = std::collections::BTreeSet::new();
        let mut returns = Vec::with_capacity(n);
        for t in 0..n {
            let r = inspect_prompt_file(dir, env, t)?;
            shapes.insert((r.trajectories, r.length_min, r.length_max));
            returns.push(r.return_mean);
        }
        let episodes = match shapes.into_iter().collect::<Vec<_>>()[..] {
            [(k, lo, hi)] if lo == hi => format!("{k} episodes of {lo} steps"),
            _ => "episodes".to_string(),
        };
        out.push_str(&format!(
            "[reference_experts.{env}]\nsource = \"official-prompts/{env}-{{0..{}}}-prompt-expert.pkl \
             of the reference release (mxu34/prompt-dt): per task, the mean return of the file's \
             {episodes} (rewards summed in f64)\"\nreturns = [\n",
            n - 1
        ));
        for (t, r) in returns.iter().enumerate() {
            // `{:?}` prints the shortest decimal that parses back to the same f64.
            out.push_str(&format!("    {r:?}, # task {t}\n"));
        }
        out.push_str("]\n");
    }
    out.push_str("# END reference_experts\n");
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_builtin_manifest_parses_and_has_the_three_budgets() {
        for (name, text) in BUILTIN {
            let m = Manifest::parse(text, name).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(m.name, *name);
            for b in ["paper", "cpu", "smoke"] {
                assert!(m.budgets.contains_key(b), "{name}: no {b} budget");
            }
        }
    }

    #[test]
    fn every_builtin_manifest_has_the_reference_experts_of_its_cheetah_cells() {
        for (name, text) in BUILTIN {
            let m = Manifest::parse(text, name).unwrap_or_else(|e| panic!("{name}: {e}"));
            for c in m.cells.iter().filter(|c| c.pending.is_none()) {
                if REFERENCE_ENVS.contains(&c.env.as_str()) {
                    assert!(m.reference_experts.contains_key(&c.env), "{name}: {}", c.env);
                    let test = pdt_envs::family(&c.env).and_then(|f| f.split("default"));
                    let (_, test) = test.unwrap_or_else(|e| panic!("{name}: {e}"));
                    assert!(m.reference_expert_returns(&c.env, &test).is_some(), "{name}");
                }
            }
            for env in m.reference_experts.keys() {
                assert!(REFERENCE_ENVS.contains(&env.as_str()), "{name}: {env}");
            }
        }
    }

    #[test]
    fn bad_reference_experts_are_refused_by_name() {
        let base = "name = 't'\ntitle = 't'\ndescription = 't'\nlayout = 'table'\n\
                    [budgets.smoke]\nnote = 'n'\n[[cells]]\nenv = 'cheetah_dir'\nmethod = 'mt-orl'\n";
        let parse = |extra: &str| Manifest::parse(&format!("{base}{extra}"), "t");
        assert!(
            parse("[reference_experts.cheetah_dir]\nsource = 's'\nreturns = [1.0, 2.0]\n").is_ok()
        );
        for (extra, want) in [
            ("[reference_experts.cheetah_dir]\nsource = 's'\nreturns = [1.0]\n", "1 values"),
            ("[reference_experts.cheetah_dir]\nsource = 's'\nreturns = [1.0, nan]\n", "returns[1]"),
            (
                "[reference_experts.cheetah_dir]\nsource = 's'\nreturns = [1.0, 1e300]\n",
                "returns[1]",
            ),
            ("[reference_experts.cheetah_dir]\nsource = ' '\nreturns = [1.0, 2.0]\n", "source"),
            ("[reference_experts.cheetah]\nsource = 's'\nreturns = [1.0]\n", "unknown environment"),
            ("[reference_experts.cheetah_dir]\nreturns = [1.0, 2.0]\n", "source"),
        ] {
            let err = parse(extra).expect_err(extra).to_string();
            assert!(err.contains(want) && err.contains("reference_experts"), "{extra}: {err}");
        }
    }

    #[test]
    fn cell_ids_name_the_variant() {
        let c = |s: &str| -> Cell { toml::from_str(s).expect("cell") };
        assert_eq!(c("env = 'cheetah_dir'\nmethod = 'prompt-dt'").id(), "cheetah_dir/prompt-dt");
        assert_eq!(
            c("env = 'ant_dir'\nsplit = 'ood'\nmethod = 'mt-orl'").id(),
            "ant_dir-ood/mt-orl"
        );
        assert_eq!(
            c("env = 'cheetah_vel'\nmethod = 'prompt-dt'\nprompt = [2, 20]\ndataset = 'medium'\ntest_prompt = 'random'").id(),
            "cheetah_vel/prompt-dt-k2x20-dmedium-prandom"
        );
        let random = c("env = 'cheetah_vel'\nmethod = 'prompt-dt'\nprompt_position = 'random'");
        assert_eq!(random.id(), "cheetah_vel/prompt-dt-posrandom");
        let tail = c("env = 'cheetah_vel'\nmethod = 'prompt-dt'\nprompt_position = 'tail'");
        assert_eq!(tail.id(), "cheetah_vel/prompt-dt", "the default keeps the cell's id");
    }

    #[test]
    fn rules_apply_in_order_and_unknown_keys_are_refused() {
        let m = Manifest::parse(
            r#"
name = "t"
title = "t"
description = "t"
layout = "curves"
[[cells]]
env = "cheetah_dir"
method = "prompt-dt"
[[cells]]
env = "cheetah_dir"
method = "mt-orl"
[budgets.smoke]
note = "n"
iterations = 2
seeds = 1
[[budgets.smoke.rules]]
methods = ["mt-orl"]
seeds = 3
[[budgets.smoke.rules]]
envs = ["cheetah_dir"]
iterations = 5
"#,
            "t",
        )
        .expect("parses");
        let s = m.settings("smoke", &m.cells[1]).expect("settings");
        assert_eq!((s.seeds, s.iterations), (Some(3), Some(5)));
        let s = m.settings("smoke", &m.cells[0]).expect("settings");
        assert_eq!((s.seeds, s.iterations), (Some(1), Some(5)));
        assert!(m.settings("paper", &m.cells[0]).is_err());
        let err = Manifest::parse("name = 'x'\nbogus = 1", "x").expect_err("unknown key");
        assert!(err.to_string().contains("bogus"), "{err}");
    }
}
