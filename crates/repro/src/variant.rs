//! Evaluation variants of a trained cell (docs/reproduce.md, "Variants"): a test-time prompt
//! strategy, or an evaluation-time adaptation, needs no training of its own. A variant cell names
//! a table merged into its base cell's `[eval]` configuration; each of the base cell's finished
//! runs (same seeds) is evaluated with the merged configuration by `promptdt eval`, in a run
//! directory of the variant's own:
//!
//! ```text
//! runs/<base id>@<variant>/<budget>/seed<N>/
//!   config.toml             the base run's configuration with the variant's [eval] merged in
//!   run.json, task_stats.json, checkpoints/latest.json   copied from the base run
//!   checkpoints/<weights>   a hard link to (or a copy of) the base run's latest weights
//!   eval_*.json             what `promptdt eval` writes (eval_final.json for the reference
//!                           rule, eval_prompt_<strategy>.json, eval_adapt_<kind>.json)
//!   eval.jsonl              that evaluation as the test evaluation of the base's last iteration
//!   variant.json            written last: the base run, the override, the file, the wall time
//! ```
//!
//! So a variant reads like any run to the report and the results registry (`eval.jsonl` at the
//! last iteration), and the base run directory is never written to.

use crate::exec_types::{ExecOptions, ExecSummary, DIE_WITH_PARENT};
use crate::plan::{self, Plan, RunSpec, RunState};
use crate::variant_spec::{BaseRun, VariantRecord, VARIANT_JSON};
use crate::ReproError;
use pdt_rundir::{EvalLine, FinalEval, RunDir};
use std::path::Path;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

/// Why `spec`'s base run cannot be evaluated yet, if it cannot: it is missing or unfinished.
fn base_not_ready(plan: &Plan, spec: &RunSpec, base: &BaseRun) -> Option<String> {
    let why = match plan.runs.iter().find(|r| r.key == base.key) {
        Some(b) => match plan::state(b) {
            Ok(RunState::Finished) => return None,
            Ok(RunState::New) => "has not run yet".to_string(),
            Ok(RunState::Partial { iteration }) => {
                format!("is not finished (iteration {iteration} of {})", b.config.train.iterations)
            }
            Err(e) => format!("cannot be read: {e}"),
        },
        None => "is not in this plan".to_string(),
    };
    Some(format!(
        "variant {}: its base run {} ({}) {why}; the variant evaluates its finished weights \
         (`reproduce {} --budget {}` trains it first)",
        spec.key,
        base.key,
        base.dir.display(),
        plan.experiment,
        plan.budget
    ))
}

/// A variant's directory made ready for `promptdt eval`: what it held before is removed (a new
/// evaluation), the base run's records copied, its latest weights linked.
fn prepare(spec: &RunSpec, base: &BaseRun) -> Result<(), ReproError> {
    let io = |p: &Path| {
        let p = p.to_path_buf();
        move |e| ReproError::Io { path: p, source: e }
    };
    let dir = &spec.dir;
    if dir.exists() {
        std::fs::remove_dir_all(dir).map_err(io(dir))?;
    }
    let (from, to) = (RunDir::at(&base.dir), RunDir::at(dir));
    std::fs::create_dir_all(to.checkpoints_dir()).map_err(io(dir))?;
    let latest = from
        .latest()?
        .ok_or_else(|| ReproError::Invalid(format!("{}: no checkpoint", base.dir.display())))?;
    for (a, b) in [
        (from.info_path(), to.info_path()),
        (from.stats_path(), to.stats_path()),
        (from.latest_path(), to.latest_path()),
    ] {
        std::fs::copy(&a, &b).map_err(io(&a))?;
    }
    let (w, w_to) = (from.checkpoint_file(&latest.model), to.checkpoint_file(&latest.model));
    // A link costs nothing; a copy where the two lie on different file systems.
    if std::fs::hard_link(&w, &w_to).is_err() {
        std::fs::copy(&w, &w_to).map_err(io(&w))?;
    }
    let text =
        spec.config.to_toml().map_err(|e| ReproError::Invalid(format!("{}: {e}", spec.key)))?;
    let path = to.config_path();
    pdt_base::fs::write_atomic(&path, text.as_bytes()).map_err(io(&path))
}

/// The evaluation file `promptdt eval` wrote into `dir` (the only one: the directory was emptied).
fn result_file(dir: &Path) -> Result<String, ReproError> {
    let entries =
        std::fs::read_dir(dir).map_err(|e| ReproError::Io { path: dir.into(), source: e })?;
    let mut found: Vec<String> = entries
        .flatten()
        .filter_map(|e| e.file_name().to_str().map(str::to_string))
        .filter(|n| {
            n == pdt_rundir::EVAL_FINAL_JSON
                || (n.ends_with(".json")
                    && (n.starts_with("eval_prompt_") || n.starts_with("eval_adapt_")))
        })
        .collect();
    found.sort();
    match found.as_slice() {
        [one] => Ok(one.clone()),
        [] => {
            Err(ReproError::Invalid(format!("{}: `promptdt eval` wrote no result", dir.display())))
        }
        many => Err(ReproError::Invalid(format!(
            "{}: several results ({}), expected one",
            dir.display(),
            many.join(", ")
        ))),
    }
}

/// After `promptdt eval` succeeded: its result as `eval.jsonl`'s test evaluation of the weights'
/// iteration, then `variant.json`.
fn finish(spec: &RunSpec, base: &BaseRun, seconds: f64) -> Result<(), ReproError> {
    let run = RunDir::at(&spec.dir);
    let file = result_file(&spec.dir)?;
    let result: FinalEval = pdt_rundir::read_json(&spec.dir.join(&file))?;
    // The target return each task was evaluated with: the variant's, where it sets one, else the
    // base run's (its last test evaluation's lines).
    let base_lines = RunDir::at(&base.dir).eval_lines()?.map(|l| l.rows).unwrap_or_default();
    let last = base_lines.iter().filter(|l| l.is_test()).map(|l| l.iteration).max();
    let target = |task: usize| -> Result<f32, ReproError> {
        if let Some(t) = spec.config.eval.target_return {
            return Ok(t);
        }
        base_lines
            .iter()
            .find(|l| l.is_test() && Some(l.iteration) == last && l.task_index == task)
            .map(|l| l.target_return)
            .ok_or_else(|| {
                ReproError::Invalid(format!(
                    "{}: no test evaluation of task {task} to take its target return from",
                    RunDir::at(&base.dir).eval_path().display()
                ))
            })
    };
    let mut lines = Vec::with_capacity(result.tasks.len());
    for t in &result.tasks {
        lines.push(EvalLine::new(
            t,
            result.iteration,
            result.step,
            &result.eval_on,
            target(t.task_index)?,
        ));
    }
    run.append_eval_lines(&lines)?;
    let record = VariantRecord {
        base: base.key.clone(),
        eval: base.eval.clone(),
        result_file: file,
        iteration: result.iteration,
        seconds,
    };
    pdt_rundir::write_json(&spec.dir.join(VARIANT_JSON), &record)?;
    Ok(())
}

/// A variant's `promptdt eval` in progress.
struct EvalJob<'p> {
    spec: &'p RunSpec,
    base: &'p BaseRun,
    child: Child,
    started: Instant,
    _parent_end: std::io::PipeWriter,
}

fn start<'p>(
    plan: &Plan,
    spec: &'p RunSpec,
    opts: &ExecOptions,
) -> Result<EvalJob<'p>, ReproError> {
    let Some(base) = spec.base.as_ref() else {
        return Err(ReproError::Invalid(format!("{}: not a variant", spec.key)));
    };
    if let Some(why) = base_not_ready(plan, spec, base) {
        return Err(ReproError::Invalid(why));
    }
    prepare(spec, base)?;
    let log_path = &spec.log_path;
    if let Some(p) = log_path.parent() {
        std::fs::create_dir_all(p).map_err(|e| ReproError::Io { path: p.into(), source: e })?;
    }
    let log = std::fs::File::create(log_path)
        .map_err(|e| ReproError::Io { path: log_path.clone(), source: e })?;
    let err = log.try_clone().map_err(|e| ReproError::Io { path: log_path.clone(), source: e })?;
    let (reader, writer) =
        std::io::pipe().map_err(|e| ReproError::Io { path: opts.exe.clone(), source: e })?;
    let mut cmd = Command::new(&opts.exe);
    cmd.arg(DIE_WITH_PARENT).args(["eval", "--run"]).arg(&spec.dir);
    cmd.args(["--device", spec.config.run.device.as_str()]);
    if base.repeats > 1 {
        // Evaluation noise apart from seed noise: the same weights over independent draws.
        cmd.args(["--repeats", &base.repeats.to_string()]);
    }
    if let Some(p) = &opts.omp_wait_policy {
        cmd.env("OMP_WAIT_POLICY", p);
    }
    let child = cmd
        .stdin(reader)
        .stdout(log)
        .stderr(err)
        .spawn()
        .map_err(|e| ReproError::Io { path: opts.exe.clone(), source: e })?;
    Ok(EvalJob { spec, base, child, started: Instant::now(), _parent_end: writer })
}

/// Evaluates the unfinished variants among `runs` (after the training: their base runs must be
/// finished), `opts.jobs` at a time. A variant that cannot be evaluated (its base run missing or
/// unfinished, its evaluation failed) goes to `summary.failed` with the reason; the others still
/// run.
pub fn evaluate(
    plan: &Plan,
    runs: &[&RunSpec],
    opts: &ExecOptions,
    summary: &mut ExecSummary,
) -> Result<(), ReproError> {
    let mut queue = std::collections::VecDeque::new();
    for r in runs {
        match plan::state(r)? {
            RunState::Finished => summary.already_finished += 1,
            _ => queue.push_back(*r),
        }
    }
    let mut running: Vec<EvalJob<'_>> = Vec::new();
    loop {
        while running.len() < opts.jobs.max(1) {
            let Some(spec) = queue.pop_front() else { break };
            match start(plan, spec, opts) {
                Ok(job) => running.push(job),
                Err(e) => summary.failed.push((spec.key.clone(), e.to_string())),
            }
        }
        if running.is_empty() {
            return Ok(());
        }
        let mut i = 0;
        while i < running.len() {
            let status = match running[i].child.try_wait() {
                Ok(Some(s)) => s,
                Ok(None) => {
                    i += 1;
                    continue;
                }
                Err(e) => {
                    return Err(ReproError::Io { path: running[i].spec.dir.clone(), source: e })
                }
            };
            let job = running.swap_remove(i);
            let key = job.spec.key.clone();
            if !status.success() {
                let log = std::fs::read_to_string(&job.spec.log_path).unwrap_or_default();
                let tail: Vec<&str> = log.lines().rev().take(5).collect();
                let tail: Vec<&str> = tail.into_iter().rev().collect();
                let message = format!(
                    "`promptdt eval` {status}; last lines of {}: {}",
                    job.spec.log_path.display(),
                    tail.join(" | ")
                );
                summary.failed.push((key, message));
                continue;
            }
            let seconds = job.started.elapsed().as_secs_f64();
            match finish(job.spec, job.base, seconds) {
                Ok(()) => summary.evaluated += 1,
                Err(e) => summary.failed.push((key, e.to_string())),
            }
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::state;
    use crate::variant_spec::with_eval;
    use pdt_rundir::config::TrainConfig;

    #[test]
    fn the_override_merges_into_eval_and_unknown_keys_are_named() {
        let base = TrainConfig::default();
        let t = |s: &str| -> toml::Table { toml::from_str(s).expect("table") };
        let c = with_eval(
            &base,
            &t("episodes = 7\n[prompt]\nstrategy = 'bandit'\n[prompt.bandit]\nrule = 'ucb'\n"),
        )
        .expect("merges");
        assert_eq!(c.eval.episodes, 7);
        assert_eq!(c.eval.prompt.strategy, pdt_prompt::PromptStrategyKind::Bandit);
        assert_eq!(c.eval.prompt.bandit.rule, pdt_prompt::BanditRule::Ucb);
        // Everything else is the base's.
        assert_eq!(c.eval.finetune_steps, base.eval.finetune_steps);
        assert_eq!(c.train, base.train);
        // A nested table merges key by key: a second override keeps the first's other keys.
        let d = with_eval(&c, &t("[prompt]\nlength = 3\n")).expect("merges");
        assert_eq!(d.eval.prompt.strategy, pdt_prompt::PromptStrategyKind::Bandit);
        assert_eq!(d.eval.prompt.length, Some(3));
        for (bad, named) in [("episode = 3", "episode"), ("[prompt]\nstrategi = 'x'", "strategi")] {
            let err = with_eval(&base, &t(bad)).expect_err(bad);
            assert!(err.contains(named) && err.starts_with("eval"), "{bad}: {err}");
        }
        let err =
            with_eval(&base, &t("[prompt]\nstrategy = 'tail'")).expect_err("unknown strategy");
        assert!(err.contains("tail"), "{err}");
    }

    const BASE: &str = "name = 't'\ntitle = 't'\ndescription = 't'\nlayout = 'table'\n\
                        [budgets.smoke]\nnote = 'n'\niterations = 2\nseeds = 2\n\
                        [[cells]]\nenv = 'cheetah_vel'\nmethod = 'prompt-dt'\n";

    fn manifest(extra: &str) -> Result<crate::Manifest, ReproError> {
        crate::Manifest::parse(&format!("{BASE}{extra}"), "t")
    }

    const BANDIT: &str = "[[cells]]\nenv = 'cheetah_vel'\nmethod = 'prompt-dt'\n\
                          variant = 'bandit'\neval = { episodes = 3, prompt = { strategy = 'bandit' } }\n";

    #[test]
    fn a_variant_names_its_base_cell_and_bad_ones_are_refused_by_name() {
        let m = manifest(BANDIT).expect("parses");
        let v = &m.cells[1];
        assert_eq!(v.id(), "cheetah_vel/prompt-dt@bandit");
        assert_eq!(v.base_id().as_deref(), Some("cheetah_vel/prompt-dt"));
        assert_eq!(m.cells[0].base_id(), None);
        assert_eq!(m.base_of(v).expect("base").map(|(i, _)| i), Some(0));
        for (extra, want) in [
            // The base cell (same fields, no variant) is not in the manifest.
            (
                "[[cells]]\nenv = 'cheetah_vel'\nmethod = 'mt-orl'\nvariant = 'x'\neval = { episodes = 3 }\n",
                "its base cell cheetah_vel/mt-orl",
            ),
            ("[[cells]]\nenv = 'cheetah_dir'\nmethod = 'prompt-dt'\neval = { episodes = 3 }\n", "give it a `variant`"),
            ("[[cells]]\nenv = 'cheetah_vel'\nmethod = 'prompt-dt'\nvariant = 'x'\n", "needs an `eval` table"),
            (
                "[[cells]]\nenv = 'cheetah_vel'\nmethod = 'prompt-dt'\nvariant = 'x'\neval = { prompt = { strategi = 'bandit' } }\n",
                "strategi",
            ),
            ("[[cells]]\nenv = 'cheetah_vel'\nmethod = 'prompt-dt'\nvariant = 'a/b'\neval = { episodes = 3 }\n", "variant \"a/b\""),
        ] {
            let err = manifest(extra).expect_err(extra).to_string();
            assert!(err.contains(want), "{extra}: {err}");
        }
        // A pending variant may name what is not built yet.
        let pending = "[[cells]]\nenv = 'cheetah_vel'\nmethod = 'prompt-dt'\nvariant = 'lora'\n\
                       eval = { adapt = { kind = 'lora' } }\npending = 'not merged'\n";
        assert!(manifest(pending).is_ok());
    }

    fn plan_of(m: &crate::Manifest) -> Plan {
        let o = crate::PlanOptions {
            budget: "smoke".into(),
            out: "/o".into(),
            data_root: "/o/data".into(),
            threads: 1,
            device: Default::default(),
            matmul: Default::default(),
            seeds: None,
        };
        plan::plan(m, &o).expect("plan")
    }

    #[test]
    fn a_variant_plans_one_evaluation_per_base_run_with_the_override_merged() {
        let p = plan_of(&manifest(BANDIT).expect("parses"));
        let keys: Vec<&str> = p.runs.iter().map(|r| r.key.as_str()).collect();
        assert_eq!(
            keys,
            [
                "cheetah_vel/prompt-dt/smoke/seed0",
                "cheetah_vel/prompt-dt/smoke/seed1",
                "cheetah_vel/prompt-dt@bandit/smoke/seed0",
                "cheetah_vel/prompt-dt@bandit/smoke/seed1",
            ]
        );
        for seed in 0..2 {
            let (b, v) = (&p.runs[seed], &p.runs[2 + seed]);
            assert!(b.base.is_none());
            let base = v.base.as_ref().expect("a variant");
            assert_eq!((base.key.as_str(), &base.dir), (b.key.as_str(), &b.dir));
            assert_eq!(
                v.dir,
                Path::new("/o/runs/cheetah_vel/prompt-dt@bandit/smoke").join(format!("seed{seed}"))
            );
            // The base run's configuration (seed, training, data), its [eval] overridden.
            assert_eq!((v.config.run.seed, &v.config.train), (b.config.run.seed, &b.config.train));
            assert_eq!(v.data, b.data);
            assert_eq!(v.config.eval.episodes, 3);
            assert_eq!(v.config.eval.prompt.strategy, pdt_prompt::PromptStrategyKind::Bandit);
            assert_eq!(
                plan::config_differences(&b.config, &v.config).len(),
                2,
                "{:?}",
                plan::config_differences(&b.config, &v.config)
            );
        }
        // A base cell not run at the budget, or pending, takes its variants with it.
        let off = "[[budgets.smoke.rules]]\nmethods = ['prompt-dt']\nrun = false\n";
        let off = manifest(&format!("{BANDIT}{off}")).expect("parses");
        let p = plan_of(&off);
        assert!(p.runs.is_empty());
        assert_eq!(p.skipped.len(), 2);
        let pending =
            BASE.replace("method = 'prompt-dt'\n", "method = 'prompt-dt'\npending = 'later'\n");
        let m = crate::Manifest::parse(&format!("{pending}{BANDIT}"), "t");
        let err = m.expect_err("a variant of a pending cell").to_string();
        assert!(err.contains("base cell cheetah_vel/prompt-dt is pending"), "{err}");
    }

    #[test]
    fn a_variant_of_an_unfinished_base_run_is_refused_naming_it() {
        let p = plan_of(&manifest(BANDIT).expect("parses"));
        let v = &p.runs[2];
        let why = base_not_ready(&p, v, v.base.as_ref().expect("variant")).expect("not ready");
        assert!(
            why.contains("cheetah_vel/prompt-dt/smoke/seed0") && why.contains("has not run yet"),
            "{why}"
        );
        assert!(why.contains("variant cheetah_vel/prompt-dt@bandit/smoke/seed0"), "{why}");
        assert_eq!(state(v).expect("state"), RunState::New);
    }
}
