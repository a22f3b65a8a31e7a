//! The report of an experiment at a budget, read from the run directories alone: ours next to the
//! paper, cell by cell, as raw returns and as normalised scores, with the paper's claims checked.
//!
//! Normalised score of a return R on test task i: `100 (R - R_random,i) / (R_expert,i - R_random,i)`,
//! with R_expert,i and R_random,i the mean returns of task i's expert and random datasets (from the
//! dataset card). A run's score is the mean over the test tasks of its last evaluation. Our experts
//! are stronger than the reference's, so raw returns are not comparable across the two; the paper's
//! numbers are normalised the same way with the reference's expert returns (its prompt files) where
//! they are known, and with our random returns (a uniform random policy in the same environment).

use crate::baselines::{archived_baselines, baselines, Baselines};
use crate::manifest::{Layout, Manifest};
use crate::plan::{self, Plan, RunState};
use crate::ReproError;
use pdt_base::table::{Align, Rule, Table};
use pdt_rundir::{EvalLine, RunDir, RunDirError};
use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

mod claims;
mod render;
use crate::stats::CellStats;
use claims::check_claim;
pub use claims::{ClaimResult, DEFAULT_MARGIN};
use render::{cells_csv, curves_csv, markdown};
pub(crate) use render::{eval_noise_text, has_paper, PaperText};

// Mean ± std over seeds (population std, as numpy's default; a diverged seed's NaN is left out
// and `n` says how many seeds were used): the rule of `promptdt report`, so one definition.
use pdt_report::Stat;

/// One cell's result.
#[derive(Debug, Clone, Serialize)]
pub struct CellResult {
    pub id: String,
    pub env: String,
    pub label: String,
    pub row: Option<String>,
    pub column: Option<String>,
    /// `ran`, `partial` (no run finished yet: the running ones are shown), `partial: N of M seeds
    /// finished` (only the finished ones are shown), `ran: N of M seeds read` (every run finished
    /// or unreadable, see `problems`), `not read: N of M seeds`, `no results yet`, or why the cell
    /// was not run.
    pub status: String,
    /// Seeds in the result: the finished ones, or while none has finished, those with at least one
    /// test evaluation.
    pub seeds: usize,
    /// Seeds whose run has finished. The paper's claims are checked only on cells with at least
    /// one: a cell whose runs are all still going says nothing yet about the trained method.
    pub seeds_finished: usize,
    /// Iteration of the last evaluation used (the smallest over seeds).
    pub iteration: Option<u64>,
    pub iterations_planned: Option<u64>,
    /// Average test return, over seeds.
    pub ours: Option<Stat>,
    /// Normalised score, over seeds: per seed the mean over test tasks of the per-task ratios
    /// (population std, as [`Stat`]).
    pub ours_normalised: Option<Stat>,
    /// Normalised score the paper's way, over seeds: per seed the ratio of means, its mean return
    /// over the test tasks normalised by the mean expert and mean random returns over those tasks
    /// (the only way a paper value, a mean over tasks, can be normalised).
    pub ours_normalised_rom: Option<Stat>,
    /// Per seed used, the per-task normalised scores of its last evaluation (what the claims'
    /// bootstrap resamples).
    pub seed_task_scores: Vec<Vec<f64>>,
    /// Sample SD, stratified-bootstrap interval and IQM of the per-task normalised scores.
    pub normalised_stats: Option<CellStats>,
    /// Success rate on the test tasks at the last evaluation, over seeds (families with a success
    /// criterion: Meta-World reach); `None` for the others.
    pub success: Option<Stat>,
    /// Evaluation noise, apart from seed noise: the spread of the normalised score over repeats
    /// of one run's evaluation (`promptdt eval --repeats`), where the cell's runs have repeats.
    pub eval_noise: Option<EvalNoise>,
    pub paper: Option<f64>,
    pub paper_std: Option<f64>,
    pub paper_source: Option<String>,
    /// The paper's value normalised with the reference's expert returns.
    pub paper_normalised: Option<f64>,
    pub paper_normalised_std: Option<f64>,
    /// Whether our normalised mean (ratio of means, the paper's way) is within the paper's
    /// (normalised) std of its value.
    pub within_paper_std: Option<bool>,
    /// `(iteration, mean over seeds, std)` of the average test return.
    pub curve: Vec<(u64, f64, f64)>,
    /// The `metrics.jsonl` column of the runs' training loss (their method's,
    /// `RunInfo::loss_metric`), where the seeds agree on one.
    pub loss_metric: Option<String>,
    /// `(iteration, mean over seeds, std)` of that loss at the iterations of [`Self::curve`]
    /// where every seed has it.
    pub loss_curve: Vec<(u64, f64, f64)>,
    /// What could not be read, by run key and file: a run left out of the result, or the dataset
    /// card the normalised scores need.
    pub problems: Vec<String>,
}

/// A cell's evaluation noise (see [`CellResult::eval_noise`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct EvalNoise {
    /// Per seed with repeats, the sample SD (n - 1) over its repeats of the normalised score (the
    /// per-task mean of ratios); pooled over those seeds as the root of the mean variance.
    pub sd: f64,
    /// Repeats per seed (the fewest among them).
    pub repeats: usize,
    /// Seeds with repeats.
    pub seeds: usize,
}

impl EvalNoise {
    /// From each seed's normalised score per repeat (seeds with fewer than 2 repeats left out).
    pub fn of(per_seed: &[Vec<f64>]) -> Option<Self> {
        let used: Vec<&Vec<f64>> = per_seed.iter().filter(|r| r.len() > 1).collect();
        let repeats = used.iter().map(|r| r.len()).min()?;
        let var = |r: &[f64]| {
            let m = mean(r);
            r.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (r.len() - 1) as f64
        };
        let pooled = used.iter().map(|r| var(r)).sum::<f64>() / used.len() as f64;
        Some(Self { sd: pooled.sqrt(), repeats, seeds: used.len() })
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub experiment: String,
    pub title: String,
    pub budget: String,
    pub budget_note: String,
    /// How the runs computed their products (`run.matmul`, one for a plan): a report of bf16 runs
    /// says so in its title and on every cell, so no bf16 result passes for an fp32 one.
    pub matmul: pdt_base::device::Matmul,
    pub cells: Vec<CellResult>,
    pub claims: Vec<ClaimResult>,
    #[serde(skip)]
    pub markdown: String,
    #[serde(skip)]
    pub files: Vec<PathBuf>,
}

/// What the report reads of one run, each of its files read once.
struct RunRecord {
    evals: Evals,
    /// The mean success rate over the test tasks of the run's last test evaluation, where its
    /// lines have one (Meta-World reach).
    last_success: Option<f64>,
    /// The run's training loss, or why it cannot be read (it is shown beside the returns only).
    loss: Result<Loss, String>,
    /// `promptdt eval --repeats`: the tasks (their indices) and, per repeat, their mean returns.
    repeats: Option<Repeats>,
}

/// The task indices of an evaluation and, per repeat, each task's mean return.
type Repeats = (Vec<usize>, Vec<Vec<f64>>);

/// A run's training loss: its column in `metrics.jsonl` and its value per iteration.
struct Loss {
    metric: String,
    by_iteration: BTreeMap<u64, f64>,
}

/// Reads the run in `dir`: its test evaluations (none while `eval.jsonl` does not exist; a line cut
/// by a kill is skipped) and its loss.
fn read_run(dir: &Path) -> Result<RunRecord, ReproError> {
    let run = RunDir::at(dir);
    let lines = run.eval_lines()?.map(|l| l.rows).unwrap_or_default();
    let test: Vec<&EvalLine> = lines.iter().filter(|l| l.is_test()).collect();
    let mut evals: Evals = BTreeMap::new();
    for l in &test {
        evals.entry(l.iteration).or_default().insert(l.task_index, l.return_mean);
    }
    let last_success = test.iter().map(|l| l.iteration).max().and_then(|last| {
        let rates: Option<Vec<f64>> =
            test.iter().filter(|l| l.iteration == last).map(|l| l.success_rate).collect();
        let rates = rates.filter(|r| !r.is_empty())?;
        Some(rates.iter().sum::<f64>() / rates.len() as f64)
    });
    let loss = read_loss(&run).map_err(|e| e.to_string());
    Ok(RunRecord { evals, last_success, loss, repeats: read_repeats(dir)? })
}

/// The repeats of a run's evaluation (`promptdt eval --repeats`), where it has them: in a
/// variant's own result file (its `variant.json` names it), else in `eval_final.json`.
fn read_repeats(dir: &Path) -> Result<Option<Repeats>, ReproError> {
    let record = dir.join(crate::variant_spec::VARIANT_JSON);
    let file = match record.is_file() {
        true => {
            let v: crate::variant_spec::VariantRecord = pdt_rundir::read_json(&record)?;
            dir.join(v.result_file)
        }
        false => RunDir::at(dir).final_eval_path(),
    };
    if !file.is_file() {
        return Ok(None);
    }
    let f: pdt_rundir::FinalEval = pdt_rundir::read_json(&file)?;
    let tasks = f.tasks.iter().map(|t| t.task_index).collect();
    Ok(f.repeats.map(|r| (tasks, r.task_returns)))
}

fn read_loss(run: &RunDir) -> Result<Loss, RunDirError> {
    let metric = run.info()?.loss_metric().to_string();
    let rows = run.metrics()?.map(|l| l.rows).unwrap_or_default();
    let by_iteration = rows.iter().filter_map(|r| Some((r.iteration, r.get(&metric)?))).collect();
    Ok(Loss { metric, by_iteration })
}

/// Per test iteration, task index -> return.
type Evals = BTreeMap<u64, BTreeMap<usize, f64>>;

/// What the report makes of one run.
enum Seen {
    /// Finished, with its evaluations (the last one is of its last iteration).
    Finished(RunRecord),
    /// Still to finish, with the evaluations so far.
    Running(RunRecord),
    /// Nothing yet.
    NotStarted,
    /// Cannot be read: what is missing or wrong, naming the file.
    Problem(String),
}

fn classify(r: &plan::RunSpec, data: &mut plan::DataCheck) -> Seen {
    let state = match plan::state(r) {
        Ok(s) => s,
        Err(e) => return Seen::Problem(e.to_string()),
    };
    let mut record = match read_run(&r.dir) {
        Ok(e) => e,
        Err(e) => return Seen::Problem(e.to_string()),
    };
    // An evaluation writes one line per test task: one with fewer was cut short (a kill, or a
    // copy taken while the run wrote it), and its mean would be over some tasks only.
    let tasks = pdt_envs::family(&r.config.env.name)
        .and_then(|f| f.split(&r.config.env.split))
        .map(|(_, test)| test.len())
        .unwrap_or(0);
    let complete = |e: &BTreeMap<usize, f64>| e.len() >= tasks;
    match state {
        RunState::New | RunState::Partial { .. } => {
            // A running run may be writing its last evaluation now: show the one before.
            while record.evals.last_key_value().is_some_and(|(_, e)| !complete(e)) {
                record.evals.pop_last();
            }
            if record.evals.is_empty() {
                Seen::NotStarted
            } else {
                Seen::Running(record)
            }
        }
        RunState::Finished => {
            if let Err(why) = data.check(r) {
                return Seen::Problem(why);
            }
            // A finished run evaluates its last iteration; an `eval.jsonl` without it was cut
            // (or left out of a copy). Its earlier evaluations would pass for the final result.
            let n = r.config.train.iterations;
            let path = RunDir::at(&r.dir).eval_path();
            match record.evals.last_key_value() {
                Some((&last, e)) if last >= n && !complete(e) => Seen::Problem(format!(
                    "finished, but {} has {} of the {tasks} test tasks of iteration {last}'s \
                     evaluation (cut short?)",
                    path.display(),
                    e.len()
                )),
                Some((&last, _)) if last >= n => Seen::Finished(record),
                Some((&last, _)) => Seen::Problem(format!(
                    "finished, but {} ends at iteration {last}'s evaluation, not {n}'s (cut short?)",
                    path.display()
                )),
                None if path.exists() => Seen::Problem(format!(
                    "finished, but {} has no test evaluation",
                    path.display()
                )),
                None => Seen::Problem(format!("finished, but {} is missing", path.display())),
            }
        }
    }
}

/// The reference release's expert return per task, where it is known: recomputed from its prompt
/// files in `dir` (`--reference DIR`) when they are there, else the numbers the manifest commits
/// (`[reference_experts]`, made from the same files), so a report needs no file of the release.
fn reference_experts(
    m: &Manifest,
    dir: Option<&Path>,
    env: &str,
    tasks: &[usize],
) -> Option<Vec<f64>> {
    let from_files = dir.and_then(|dir| {
        tasks
            .iter()
            .map(|t| crate::manifest::reference_expert_return(dir, env, *t).ok())
            .collect::<Option<Vec<f64>>>()
    });
    from_files.or_else(|| m.reference_expert_returns(env, tasks))
}

fn normalise(r: f64, expert: f64, random: f64) -> f64 {
    100.0 * (r - random) / (expert - random)
}

/// Builds the report from the run directories of `plan` and writes it into its report directory.
pub fn report(
    m: &Manifest,
    plan: &Plan,
    reference_dir: Option<&Path>,
) -> Result<Report, ReproError> {
    let mut rep = build(m, plan, reference_dir)?;
    write_outputs(m, plan, &mut rep)?;
    Ok(rep)
}

/// The report of `plan`'s run directories, written nowhere (`results render` reads it).
pub fn build(
    m: &Manifest,
    plan: &Plan,
    reference_dir: Option<&Path>,
) -> Result<Report, ReproError> {
    let budget = m.budget(&plan.budget)?;
    let mut reader = CellReader {
        m,
        plan,
        reference_dir,
        base_cache: BTreeMap::new(),
        data_check: plan::DataCheck::default(),
    };
    let cells: Vec<CellResult> =
        m.cells.iter().enumerate().filter_map(|(i, cell)| reader.cell(i, cell)).collect();
    let claims = m.claims.iter().map(|c| check_claim(c, &cells)).collect();
    let mut rep = Report {
        experiment: m.name.clone(),
        title: m.title.clone(),
        budget: plan.budget.clone(),
        budget_note: budget.note.clone(),
        matmul: plan.runs.first().map(|r| r.config.run.matmul).unwrap_or_default(),
        cells,
        claims,
        markdown: String::new(),
        files: Vec::new(),
    };
    rep.markdown = markdown(m, &rep);
    Ok(rep)
}

/// Reads the cells of a plan, the datasets' baselines read once per data directory.
struct CellReader<'a> {
    m: &'a Manifest,
    plan: &'a Plan,
    reference_dir: Option<&'a Path>,
    base_cache: BTreeMap<PathBuf, Result<Baselines, String>>,
    data_check: plan::DataCheck,
}

/// A cell's seeds as read: per seed its last evaluation's mean, scores and curve.
#[derive(Default)]
struct Seeds<'r> {
    finals: Vec<f64>,
    norms: Vec<f64>,
    norms_rom: Vec<f64>,
    successes: Vec<f64>,
    curves: Vec<BTreeMap<u64, f64>>,
    losses: Vec<&'r Loss>,
    /// Per seed with `promptdt eval --repeats`: the normalised score of each repeat.
    repeat_scores: Vec<Vec<f64>>,
    /// The earliest of the seeds' last evaluated iterations.
    last_iter: Option<u64>,
}

impl CellReader<'_> {
    /// Cell `i`'s result; `None` for a cell the plan has no run of.
    fn cell(&mut self, i: usize, cell: &crate::manifest::Cell) -> Option<CellResult> {
        let mut res = CellResult::empty(cell);
        if let Some(s) = self.plan.skipped.iter().find(|s| s.cell == i) {
            res.status = s.reason.clone();
            return Some(res);
        }
        let runs: Vec<&plan::RunSpec> = self.plan.runs.iter().filter(|r| r.cell == i).collect();
        let first = runs.first()?;
        res.iterations_planned = Some(first.config.train.iterations);
        let (base, base_missing) = self.baselines(&runs);
        // While a sweep runs, its finished seeds are the cell's result and the seeds still running
        // are left out (their last evaluation is from an earlier iteration: mixing them in would
        // average a 2000-iteration model with a 1-iteration one). With no seed finished yet, the
        // running ones are shown, marked partial. A run that cannot be read (a half-written or
        // half-copied tree) is neither: it is left out and named.
        let seen: Vec<Seen> = runs.iter().map(|r| classify(r, &mut self.data_check)).collect();
        let n_finished = seen.iter().filter(|s| matches!(s, Seen::Finished(_))).count();
        let n_waiting =
            seen.iter().filter(|s| matches!(s, Seen::Running(_) | Seen::NotStarted)).count();
        for (r, s) in runs.iter().zip(&seen) {
            if let Seen::Problem(why) = s {
                res.problems.push(format!("{}: {why}", r.key));
            }
        }
        let used: Vec<(&plan::RunSpec, &RunRecord)> = runs
            .iter()
            .zip(&seen)
            .filter_map(|(r, s)| match s {
                Seen::Finished(e) => Some((*r, e)),
                Seen::Running(e) if n_finished == 0 => Some((*r, e)),
                _ => None,
            })
            .collect();
        let seeds = read_seeds(&mut res, &used, base.as_ref());
        res.seeds = seeds.finals.len();
        if let (Some(why), false) = (base_missing, seeds.finals.is_empty()) {
            res.problems.push(match why.starts_with("not normalised") {
                // A suite's own reason (`suite_baselines`): no data directory would change it.
                true => why,
                false => {
                    format!("no normalised score: {why} (--data-root names where the data are)")
                }
            });
        }
        res.seeds_finished = n_finished;
        res.iteration = seeds.last_iter;
        res.ours = Stat::of(&seeds.finals);
        res.ours_normalised = Stat::of(&seeds.norms);
        res.ours_normalised_rom = Stat::of(&seeds.norms_rom);
        res.normalised_stats = crate::stats::cell_stats(&res.seed_task_scores);
        res.eval_noise = EvalNoise::of(&seeds.repeat_scores);
        // Only where every seed's run reports a success rate.
        if seeds.successes.len() == seeds.finals.len() {
            res.success = Stat::of(&seeds.successes);
        }
        res.status = status(runs.len(), n_finished, n_waiting, res.seeds);
        curves(&mut res, &seeds);
        if let Some(b) = &base {
            self.paper_normalised(&mut res, cell, b);
        }
        Some(res)
    }

    /// The random and expert returns the cell's runs are scored with, or why there are none.
    fn baselines(&mut self, runs: &[&plan::RunSpec]) -> (Option<Baselines>, Option<String>) {
        // A suite's runs: its own declared returns; where it declares none, its data's card (what
        // `promptdt collect` measured), as a built-in family's; neither: "not normalised".
        let suite_why =
            match crate::baselines::suite_baselines(&runs[0].config.env.name, &runs[0].dir) {
                Some(Ok(b)) => return (Some(b), None),
                Some(Err(why)) => Some(why),
                None => None,
            };
        let dir = &runs[0].data.dir;
        let base = match self.base_cache.get(dir) {
            Some(b) => b.clone(),
            None => {
                let b = baselines(dir).map_err(|e| e.to_string());
                self.base_cache.insert(dir.clone(), b.clone());
                b
            }
        };
        // Without the dataset card there is no normalised score: say which card is missing (a
        // tree copied without its data, or a `--data-root` that names another place).
        // An archived run (the results registry) carries the card's returns it was scored with.
        let base =
            base.or_else(|why| runs.iter().find_map(|r| archived_baselines(&r.dir)).ok_or(why));
        match (base, suite_why) {
            (Ok(b), _) => (Some(b), None),
            (Err(why), None) => (None, Some(why)),
            (Err(_), Some(why)) => {
                (None, Some(format!("{why}, and its data have no dataset card")))
            }
        }
    }

    /// The paper's number normalised as ours are (with the reference's experts where known), and
    /// whether ours is within the paper's spread of it.
    fn paper_normalised(&self, res: &mut CellResult, cell: &crate::manifest::Cell, b: &Baselines) {
        let test_tasks = self
            .m
            .family(&cell.env)
            .and_then(|f| f.split(cell.split.as_deref().unwrap_or("default")))
            .map(|(_, test)| test)
            .unwrap_or_default();
        if let Some(p) = cell.paper {
            let randoms: Option<Vec<f64>> =
                test_tasks.iter().map(|t| b.random.get(t).copied()).collect();
            let experts = reference_experts(self.m, self.reference_dir, &cell.env, &test_tasks);
            if let (Some(rand), Some(exp)) = (randoms, experts) {
                let (r, e) = (mean(&rand), mean(&exp));
                res.paper_normalised = Some(normalise(p, e, r));
                res.paper_normalised_std = cell.paper_std.map(|s| 100.0 * s / (e - r));
            }
        }
        if let (Some(o), Some(p), Some(s)) =
            (res.ours_normalised_rom, res.paper_normalised, res.paper_normalised_std)
        {
            res.within_paper_std = Some((o.mean - p).abs() <= s);
        }
    }
}

/// Per seed: the last evaluation (its mean, normalised scores and success rate), every evaluation
/// for the curve, and the loss; the per-task scores go into `res`, problems too.
fn read_seeds<'r>(
    res: &mut CellResult,
    used: &[(&plan::RunSpec, &'r RunRecord)],
    base: Option<&Baselines>,
) -> Seeds<'r> {
    let mut s = Seeds::default();
    for &(r, record) in used {
        let evals = &record.evals;
        let Some((&it, last)) = evals.iter().next_back() else { continue };
        s.last_iter = Some(s.last_iter.map_or(it, |l: u64| l.min(it)));
        let avg = last.values().sum::<f64>() / last.len() as f64;
        s.finals.push(avg);
        s.successes.extend(record.last_success);
        // Not prefixed by the run's key: the run is not left out, only its loss is not shown.
        match &record.loss {
            Ok(l) => s.losses.push(l),
            Err(why) => res.problems.push(format!("no loss curve for {}: {why}", r.key)),
        }
        if let Some(b) = base {
            let n: Option<Vec<f64>> = last
                .iter()
                .map(|(t, r)| Some(normalise(*r, *b.expert.get(t)?, *b.random.get(t)?)))
                .collect();
            if let Some(n) = n {
                s.norms.push(n.iter().sum::<f64>() / n.len() as f64);
                res.seed_task_scores.push(n);
            }
            let cards: Option<(Vec<f64>, Vec<f64>)> = last
                .keys()
                .map(|t| Some((*b.expert.get(t)?, *b.random.get(t)?)))
                .collect::<Option<Vec<_>>>()
                .map(|v| v.into_iter().unzip());
            if let Some((e, r)) = cards {
                s.norms_rom.push(normalise(avg, mean(&e), mean(&r)));
            }
            // Per repeat, the normalised score as above (the per-task mean of ratios).
            if let Some((tasks, rows)) = &record.repeats {
                let score = |row: &Vec<f64>| -> Option<f64> {
                    let n: Option<Vec<f64>> = tasks
                        .iter()
                        .zip(row)
                        .map(|(t, r)| Some(normalise(*r, *b.expert.get(t)?, *b.random.get(t)?)))
                        .collect();
                    n.map(|n| mean(&n))
                };
                if let Some(scores) = rows.iter().map(score).collect::<Option<Vec<f64>>>() {
                    s.repeat_scores.push(scores);
                }
            }
        }
        s.curves.push(
            evals
                .iter()
                .map(|(it, tasks)| (*it, tasks.values().sum::<f64>() / tasks.len() as f64))
                .collect(),
        );
    }
    s
}

/// A cell's status from its seeds: `partial` only while a seed is still to run (a finished run is
/// never called partial, and one that cannot be read is counted apart and named in `problems`).
fn status(runs: usize, n_finished: usize, n_waiting: usize, seeds: usize) -> String {
    let n_problems = runs - n_finished - n_waiting;
    if n_finished == runs {
        "ran".into()
    } else if n_finished > 0 && n_waiting == 0 {
        format!("ran: {n_finished} of {runs} seeds read")
    } else if n_finished > 0 {
        format!("partial: {n_finished} of {runs} seeds finished")
    } else if seeds > 0 {
        "partial".into()
    } else if n_problems > 0 {
        format!("not read: {n_problems} of {runs} seeds")
    } else {
        "no results yet".into()
    }
}

/// The cell's learning curve (at the iterations every seed evaluated), and the loss beside it
/// where every seed read has it under one column name.
fn curves(res: &mut CellResult, s: &Seeds<'_>) {
    if let Some(first_curve) = s.curves.first() {
        for it in first_curve.keys() {
            let v: Vec<f64> = s.curves.iter().filter_map(|c| c.get(it).copied()).collect();
            if v.len() == s.curves.len() {
                if let Some(st) = Stat::of(&v) {
                    res.curve.push((*it, st.mean, st.std));
                }
            }
        }
    }
    let metric = s.losses.first().map(|l| l.metric.clone());
    if s.losses.len() == s.curves.len()
        && s.losses.iter().all(|l| Some(&l.metric) == metric.as_ref())
    {
        for &(it, _, _) in &res.curve {
            let v: Vec<f64> =
                s.losses.iter().filter_map(|l| l.by_iteration.get(&it).copied()).collect();
            if v.len() == s.losses.len() {
                if let Some(st) = Stat::of(&v) {
                    res.loss_curve.push((it, st.mean, st.std));
                }
            }
        }
        res.loss_metric = metric;
    }
}

impl CellResult {
    /// The cell as the manifest states it, with nothing read yet.
    fn empty(cell: &crate::manifest::Cell) -> Self {
        CellResult {
            id: cell.id(),
            env: cell.env.clone(),
            label: cell.label(),
            row: cell.row.clone(),
            column: cell.column.clone(),
            status: String::new(),
            seeds: 0,
            seeds_finished: 0,
            iteration: None,
            iterations_planned: None,
            ours: None,
            ours_normalised: None,
            ours_normalised_rom: None,
            seed_task_scores: Vec::new(),
            normalised_stats: None,
            success: None,
            eval_noise: None,
            paper: cell.paper,
            paper_std: cell.paper_std,
            paper_source: cell.paper_source.clone(),
            paper_normalised: None,
            paper_normalised_std: None,
            within_paper_std: None,
            curve: Vec::new(),
            loss_metric: None,
            loss_curve: Vec::new(),
            problems: Vec::new(),
        }
    }
}

/// Writes `rep`'s files (Markdown, CSV, JSON, curves) into `plan`'s report directory.
fn write_outputs(m: &Manifest, plan: &Plan, rep: &mut Report) -> Result<(), ReproError> {
    let mut outputs: Vec<(String, Vec<u8>)> = vec![
        ("report.md".into(), rep.markdown.clone().into_bytes()),
        ("cells.csv".into(), cells_csv(rep).into_bytes()),
        ("curves.csv".into(), curves_csv(rep).into_bytes()),
        ("report.json".into(), serde_json::to_string_pretty(&rep).unwrap_or_default().into_bytes()),
    ];
    if m.layout == Layout::Curves || rep.cells.iter().any(|c| c.curve.len() > 1) {
        // A panel per environment and split (the part of the cell id before the method), so
        // Ant-Dir's two OOD splits get a panel each.
        let panel = |c: &CellResult| c.id.split('/').next().unwrap_or(&c.env).to_string();
        let mut envs: Vec<String> = Vec::new();
        for c in &rep.cells {
            if !envs.contains(&panel(c)) {
                envs.push(panel(c));
            }
        }
        for env in envs {
            let of_env: Vec<&CellResult> = rep.cells.iter().filter(|c| panel(c) == env).collect();
            let mut series: Vec<pdt_report::Series> = of_env
                .iter()
                .filter(|c| !c.curve.is_empty())
                .map(|c| pdt_report::Series {
                    name: c.label.clone(),
                    sub: format!("{} seed{}", c.seeds, if c.seeds == 1 { "" } else { "s" }),
                    points: c.curve.iter().map(|(i, m, s)| (*i as f64, *m, *s)).collect(),
                })
                .collect();
            if series.is_empty() {
                continue;
            }
            let x_end =
                series.iter().flat_map(|s| s.points.iter().map(|p| p.0)).fold(1.0_f64, f64::max);
            for c in of_env.iter().filter(|c| !c.curve.is_empty()) {
                if let Some(p) = c.paper {
                    series.push(pdt_report::Series {
                        name: format!("paper: {}", c.label),
                        sub: match c.paper_source.as_deref() {
                            Some(src) if src.contains("approx") => "paper, approximate".into(),
                            Some(src) => format!("paper, {src}"),
                            None => "paper".into(),
                        },
                        points: vec![(0.0, p, 0.0), (x_end, p, 0.0)],
                    });
                }
            }
            let stem = env.replace(|c: char| !c.is_ascii_alphanumeric() && c != '_', "_");
            let fig = pdt_report::learning_curves(
                &format!("{} ({} budget): {env}", m.title, plan.budget),
                "Average return on test tasks",
                &series,
                &[
                    "line: mean over seeds, band: ± std".to_string(),
                    "flat lines: the paper's final values".to_string(),
                ],
                &format!("curves_{stem}.png"),
            )
            .map_err(|e| ReproError::Invalid(e.to_string()))?;
            outputs.push((format!("curves_{stem}.png"), fig.png));
            outputs.push((format!("curves_{stem}.svg"), fig.svg.into_bytes()));
        }
    }
    rep.files = pdt_report::write_files(&plan.report_dir(), &outputs)
        .map_err(|e| ReproError::Invalid(e.to_string()))?;
    Ok(())
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}
