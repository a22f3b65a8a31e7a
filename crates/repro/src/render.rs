//! `RESULTS.md` and the README's headline block, generated from the results registry
//! ([`crate::registry`]) alone: every number in them is an archived run's, read by the same report
//! `reproduce --report-only` writes. `crates/repro/tests/it/results_md.rs` regenerates both and fails
//! when the committed files differ.

use crate::manifest::{Manifest, BUILTIN};
use crate::plan::{self, PlanOptions};
use crate::registry;
use crate::report::{self, Report};
use crate::stats;
use crate::ReproError;
use pdt_report::Stat;
use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

mod archive;

/// The README's generated block lies between these lines.
pub const README_BEGIN: &str = "<!-- results:begin -->";
pub const README_END: &str = "<!-- results:end -->";
/// The experiment whose rows the README's headline block shows.
const HEADLINE_EXPERIMENT: &str = "fig2";
/// The experiment whose table always has the evaluation-noise column, and whose table
/// docs/prompt-control.md quotes (between these lines).
const NOISE_EXPERIMENT: &str = "prompt_control";
pub const PROMPT_CONTROL_BEGIN: &str = "<!-- prompt-control:begin -->";
pub const PROMPT_CONTROL_END: &str = "<!-- prompt-control:end -->";

/// What `promptdt results render` writes.
#[derive(Debug, Clone)]
pub struct Rendered {
    pub results_md: String,
    /// The README's block, markers excluded.
    pub readme_block: String,
    /// docs/prompt-control.md's block (the prompt-control table), markers excluded.
    pub prompt_control_block: String,
}

/// One experiment at one budget, read from the registry.
struct Section {
    report: Report,
    /// Per cell id: the archived runs' seeds and the devices that ran them.
    seeds: BTreeMap<String, Vec<u64>>,
    devices: BTreeMap<String, BTreeSet<String>>,
    /// Per cell id and device: each archived run's wall time (seconds, `provenance.json`) and how
    /// many runs shared its device, so that what a run costs is read from the archive, never typed.
    walls: BTreeMap<String, archive::Walls>,
    /// Per cell id the budget plans runs for: how many seeds it plans (what the archive is
    /// described against).
    planned: Vec<(String, usize)>,
}

/// Every committed experiment at every budget with an archived run, then every user experiment
/// whose manifest the archives record ([`user_manifests`]), as reported from the registry in
/// `registry` (no run directory, data or checkpoint is read; a user experiment's manifest and
/// suite files are).
///
/// An archived run that cannot be read (a cut `eval.jsonl`, a garbage `config.toml`, a corrupt
/// `provenance.json` or `normalisation.json`: any file of it the report reads) fails the whole
/// render, every such run named with its file and why: `RESULTS.md` is committed, and a row
/// silently left out (or a device shown as `-`) would publish another result than the registry
/// holds.
fn sections(registry: &Path) -> Result<(Vec<Section>, Vec<UserExperiment>), ReproError> {
    // A registry that is not there, or holds no archived run, would render an empty RESULTS.md
    // over the committed one: a mistyped `--registry`, never an intended result.
    if !registry.is_dir() {
        return Err(ReproError::Invalid(format!(
            "--registry {}: no such directory (the results registry, `results/` in the \
             repository); nothing written",
            registry.display()
        )));
    }
    let archived: BTreeSet<String> = registry::keys(registry).into_iter().collect();
    if archived.is_empty() {
        return Err(ReproError::Invalid(format!(
            "--registry {}: holds no archived run (no <cell id>/<budget>/seed<N>/{} under it); \
             nothing written",
            registry.display(),
            registry::PROVENANCE_JSON
        )));
    }
    // Problem -> where it was met (`fig2 cpu`): a run read by two experiments is named once.
    let mut problems = Problems::new();
    let mut out = Vec::new();
    for (name, _) in BUILTIN {
        let m = Manifest::load(name)?;
        out.extend(experiment_sections(&m, registry, &archived, &mut problems)?);
    }
    let mut users = Vec::new();
    for (manifest, m, keys) in user_manifests(registry, &archived, &mut problems) {
        let sections = experiment_sections(&m, registry, &keys, &mut problems)
            .map_err(|e| ReproError::Invalid(format!("{manifest}: {e}")))?;
        if !sections.is_empty() {
            users.push(UserExperiment { manifest, m, sections });
        }
    }
    for key in registry::strays(registry) {
        let why = format!(
            "{key}: no {} (a run's directory without its record)",
            registry::PROVENANCE_JSON
        );
        problems.entry(why).or_default().insert("every experiment".into());
    }
    if !problems.is_empty() {
        let list: Vec<String> = problems
            .iter()
            .map(|(why, at)| {
                let at: Vec<&str> = at.iter().map(String::as_str).collect();
                format!("  {why} (read for {})", at.join(", "))
            })
            .collect();
        return Err(ReproError::Invalid(format!(
            "{}: {} archived run file(s) cannot be read, so RESULTS.md would leave their runs out \
             or show them wrong; nothing written. Archive each run again from its run directory \
             (`promptdt results add`), or remove its directory from the registry:\n{}",
            registry.display(),
            list.len(),
            list.join("\n")
        )));
    }
    Ok((out, users))
}

/// Problem -> the experiments (and budgets) it was met for.
type Problems = BTreeMap<String, BTreeSet<String>>;

/// Where the problems of finding the user experiments are said to be met.
const USER_EXPERIMENTS: &str = "the user experiments";

/// A user's experiment with archived runs (docs/reproduce.md, "Your own experiments"): its
/// manifest as the archives' `provenance.json` records it, the manifest read, and a section per
/// budget with an archived run.
struct UserExperiment {
    manifest: String,
    m: Manifest,
    sections: Vec<Section>,
}

/// The user experiments the registry's archives record (`provenance.json`'s `manifest`), in the
/// order of their recorded paths: the recorded path, the manifest read from it, and the keys of
/// the archives recording it. What keeps one from being rendered is a problem naming the archive
/// and the file: an archive of an experiment that is no built-in one and records no manifest (its
/// runs would be left out unsaid), a manifest file that is gone or cannot be read, or one that now
/// names another experiment than its archives.
fn user_manifests(
    registry: &Path,
    archived: &BTreeSet<String>,
    problems: &mut Problems,
) -> Vec<(String, Manifest, BTreeSet<String>)> {
    let mut problem = |why: String| {
        problems.entry(why).or_default().insert(USER_EXPERIMENTS.into());
    };
    // Recorded manifest -> the experiment names its archives record, and their keys.
    let mut recorded: BTreeMap<String, (BTreeSet<String>, BTreeSet<String>)> = BTreeMap::new();
    for key in archived {
        let dir = registry.join(key);
        let pv = match registry::provenance(&dir) {
            Ok(pv) => pv,
            // The message the paper's experiments give it, so the run is named once.
            Err(e) => {
                problem(format!("{key}: {e}"));
                continue;
            }
        };
        match pv.manifest {
            Some(file) => {
                let (names, keys) = recorded.entry(file).or_default();
                names.insert(pv.experiment);
                keys.insert(key.clone());
            }
            None if registry::is_builtin(&pv.experiment) => {}
            None => problem(format!(
                "{key}: {}: experiment `{}` is no built-in one and the record names no manifest \
                 file (archived before `results add --exp FILE` recorded it), so its section \
                 cannot be rendered: archive the run again with `results add --exp FILE`, or write \
                 the file's path from {} into it as \"manifest\" (docs/reproduce.md#the-results-\
                 registry)",
                dir.join(registry::PROVENANCE_JSON).display(),
                pv.experiment,
                registry::registry_root(registry).display()
            )),
        }
    }
    let root = registry::registry_root(registry);
    let mut out = Vec::new();
    for (file, (names, keys)) in recorded {
        let path = root.join(&file);
        let names = names.into_iter().collect::<Vec<_>>().join("`, `");
        let runs = keys.iter().cloned().collect::<Vec<_>>().join(", ");
        let loaded = match path.is_file() {
            true => Manifest::load(&path.to_string_lossy()).map_err(|e| e.to_string()),
            false => Err("no such file".to_string()),
        };
        match loaded {
            Ok(m) if names == m.name => out.push((file, m, keys)),
            Ok(m) => problem(format!(
                "{}: the manifest of experiment `{names}` recorded by {runs} (their \
                 provenance.json's \"manifest\") now names experiment `{}`",
                path.display(),
                m.name
            )),
            Err(e) => problem(format!(
                "{}: the manifest of experiment `{names}` recorded by {runs} (their \
                 provenance.json's \"manifest\") cannot be read: {e}; put it back, or archive the \
                 runs again with `results add --exp FILE` naming where it is now",
                path.display()
            )),
        }
    }
    out
}

/// The sections of experiment `m`, one per budget with an archived run among `archived` (keys),
/// as reported from the registry in `registry` (no run directory, data or checkpoint is read).
/// What its runs' files cannot give is added to `problems`.
fn experiment_sections(
    m: &Manifest,
    registry: &Path,
    archived: &BTreeSet<String>,
    problems: &mut Problems,
) -> Result<Vec<Section>, ReproError> {
    // A place with no run directories, so that every run is read from the registry.
    let nowhere = registry.join(".no-run-directories");
    let mut out = Vec::new();
    for b in m.budgets.keys() {
        let opts = PlanOptions {
            budget: b.clone(),
            out: nowhere.clone(),
            data_root: nowhere.join("data"),
            threads: 1,
            device: Default::default(),
            matmul: Default::default(),
            seeds: None,
        };
        // Every archived seed, however many the budget plans: the registry's runs only.
        let Some(max_seed) = registry::max_seed(archived, b) else { continue };
        let mut planned: Vec<(String, usize)> = Vec::new();
        for r in &plan::plan(m, &opts)?.runs {
            let id = m.cells[r.cell].id();
            match planned.iter_mut().find(|(c, _)| *c == id) {
                Some((_, n)) => *n += 1,
                None => planned.push((id, 1)),
            }
        }
        let mut p = plan::plan(m, &PlanOptions { seeds: Some(max_seed + 1), ..opts })?;
        p.runs.retain(|r| archived.contains(&r.key));
        let used = registry::use_archived(&mut p, registry);
        if used.is_empty() {
            continue;
        }
        let rep = report::build(m, &p, None)?;
        let at = format!("{} `{b}`", m.name);
        for c in &rep.cells {
            for why in &c.problems {
                // The report's problems start with the run's key, or name the cell's card.
                let why = match why.starts_with(&format!("{}/", c.id)) {
                    true => why.clone(),
                    false => format!("{}: {why}", c.id),
                };
                problems.entry(why).or_default().insert(at.clone());
            }
        }
        let mut seeds: BTreeMap<String, Vec<u64>> = BTreeMap::new();
        let mut devices: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        let mut walls: BTreeMap<String, archive::Walls> = BTreeMap::new();
        for r in p.runs.iter().filter(|r| used.contains(&r.key)) {
            let id = m.cells[r.cell].id();
            seeds.entry(id.clone()).or_default().push(r.seed);
            if let Ok(pv) = registry::provenance(&r.dir) {
                let by_device = walls.entry(id.clone()).or_default();
                by_device
                    .entry(pv.device_name.clone())
                    .or_default()
                    .push((pv.wall_time_s, pv.shared_with));
                devices.entry(id).or_default().insert(pv.device_name);
            }
            for why in registry::archive_problems(&r.dir, r.base.is_some()) {
                problems.entry(format!("{}: {why}", r.key)).or_default().insert(at.clone());
            }
        }
        out.push(Section { report: rep, seeds, devices, walls, planned });
    }
    Ok(out)
}

fn stat(s: Option<Stat>, d: usize) -> String {
    s.map_or("-".into(), |s| {
        if s.n > 1 {
            format!("{:.d$} ± {:.d$}", s.mean, s.std)
        } else {
            format!("{:.d$}", s.mean)
        }
    })
}

fn seeds_text(seeds: &[u64]) -> String {
    let list = seeds.iter().map(u64::to_string).collect::<Vec<_>>().join(", ");
    format!("{} ({list})", seeds.len())
}

/// What the task-blind fits mean: no number (they are in the generated table above it), and
/// nothing the table does not show.
const MT_ORL_READING: &str = "Reading: MT-ORL sees no prompt, so it cannot tell the test tasks \
apart. Where a fit's residual is small against the span of the task returns, the run acted alike \
on every test task at that iteration, and each task's return follows how far its goal lies from \
that one behaviour; a run whose mean falls while its fits stay tight is a task-blind policy \
settling on a behaviour that suits the test goals worse, not one that unlearned them. A speed fit \
marked not identified sits on the edge of the searched targets: the returns do not pin the speed \
down. Not measured here: what a paper-budget MT-ORL run ends at, or whether the reference code's \
own MT-ORL behaves alike at this budget.";

fn opt(v: Option<f64>) -> String {
    v.map_or("-".into(), |v| format!("{v:.1}"))
}

/// The cell's normalised mean ± sample SD (per-task mean of ratios), its interval and IQM.
fn normalised_text(c: &report::CellResult) -> (String, String, String) {
    match &c.normalised_stats {
        Some(st) => (
            match st.sd {
                Some(sd) => format!("{:.1} ± {sd:.1}", st.mean),
                None => format!("{:.1}", st.mean),
            },
            st.ci.to_string(),
            opt(st.iqm),
        ),
        None => (stat(c.ours_normalised, 1), "-".into(), "-".into()),
    }
}

/// `RESULTS.md` and the README block from the registry in `registry`.
pub fn render(registry: &Path) -> Result<Rendered, ReproError> {
    let (sections, users) = sections(registry)?;
    let mut s = String::new();
    let _ = writeln!(s, "# Results\n");
    let _ = writeln!(
        s,
        "Generated by `promptdt results render` from the results registry ([`results/`](results)), \
         never typed: every number is an archived run's, reported as `promptdt reproduce EXP \
         --budget B --report-only` reports it (on a fresh clone too: it reads the registry where a \
         run directory is absent). Each archived run keeps its configuration, evaluations, a \
         thinned training curve, the dataset returns it was normalised with and its provenance \
         (`provenance.json`: commit, device, libtorch, wall time). Normalised: 100 = the task's \
         expert data, 0 = random ([docs/reproduce.md](docs/reproduce.md#normalised-scores)); the \
         paper's value is normalised with the reference release's experts where they are known.\n"
    );
    let _ = writeln!(
        s,
        "Columns: *ours*: mean ± population std over seeds of the average test return. *ours \
         normalised*: per seed the mean over test tasks of each task's normalised score (the \
         per-task mean of ratios), then mean ± sample SD over seeds; the claims use it. *{:.0} % \
         interval*: of that mean, by a stratified bootstrap over seeds x tasks ({} resamples, \
         seeded; docs/reproduce.md#claims). *IQM*: interquartile mean of the seeds' per-task \
         scores pooled, shown where a cell has at least {} seeds. *ours, ratio of means*: per seed \
         the mean test return normalised by the mean expert and mean random returns over the test \
         tasks, the only way the paper's value (a mean over tasks) can be normalised, so the one \
         compared with *paper normalised*. *evaluation noise* (the prompt-control table, and any \
         table with a cell evaluated more than once): per seed the sample SD of *ours normalised* \
         over repeats of the same weights' evaluation (`promptdt eval --repeats`: independent \
         prompt draws and reset seeds), pooled over seeds; `-` where the runs were evaluated once.\n",
        100.0 * stats::CONFIDENCE,
        stats::RESAMPLES,
        stats::MIN_SEEDS
    );
    for sec in &sections {
        let heading = format!("## {} — `{}` budget", sec.report.title, sec.report.budget);
        cells_table(&mut s, sec, &heading);
    }
    let _ = writeln!(s, "## What reproduces\n");
    let _ = writeln!(
        s,
        "The paper's claims, judged on the per-task normalised scores of the archived runs \
         (docs/reproduce.md#claims): a \"beats\" claim **holds** when the {:.0} % bootstrap \
         interval of the difference lies above its margin ({} normalised points unless the \
         manifest says otherwise), **fails** when it lies below, and is **undecided** when it \
         contains the margin; a \"similar\" claim holds only when the interval lies inside ± the \
         margin (an equivalence test). With fewer than {} seeds on a side a verdict reads \
         **provisional (n vs m seeds)**, and the detail says what the interval alone says. Ours \
         against the paper's value: ours as a ratio of means, the paper's way.\n",
        100.0 * stats::CONFIDENCE,
        report::DEFAULT_MARGIN,
        stats::MIN_SEEDS
    );
    for sec in &sections {
        verdicts(&mut s, sec);
    }
    if let Some(blind) = crate::task_blind::section(registry)? {
        let _ = writeln!(s, "\n## Why MT-ORL rises and then falls\n");
        s.push_str(&blind);
        let _ = writeln!(s, "\n{MT_ORL_READING}");
    }
    for u in &users {
        user_section(&mut s, u);
    }
    let _ = writeln!(
        s,
        "\nRows appear only for archived runs. Numbers measured earlier on machines whose runs were \
         not archived are in this file's and README.md's git history."
    );
    let prompt_control_block = prompt_control(&sections);
    Ok(Rendered { results_md: s, readme_block: headline(&sections), prompt_control_block })
}

/// docs/prompt-control.md's table: per budget with archived runs, the prompt-control rows by
/// column, each the normalised score (per-task mean of ratios, mean over seeds), its seeds and its
/// evaluation noise; RESULTS.md has the rest (raw returns, intervals, devices, the claims).
fn prompt_control(sections: &[Section]) -> String {
    let mut s = String::new();
    for sec in sections.iter().filter(|sec| sec.report.experiment == NOISE_EXPERIMENT) {
        let r = &sec.report;
        let mut rows: Vec<&str> = Vec::new();
        let mut cols: Vec<&str> = Vec::new();
        for c in &r.cells {
            if let (Some(row), Some(col)) = (c.row.as_deref(), c.column.as_deref()) {
                if !rows.contains(&row) {
                    rows.push(row);
                }
                if !cols.contains(&col) {
                    cols.push(col);
                }
            }
        }
        let _ = writeln!(
            s,
            "At the `{}` budget, from the registry: normalised score (100 = the task's expert \
             data, 0 = random; per-task mean of ratios, mean over seeds), then in brackets the \
             seeds and, where measured, the evaluation noise (SD over repeats of one run's \
             evaluation); `-`: no archived run.\n",
            r.budget
        );
        let _ = writeln!(s, "| row | {} |", cols.join(" | "));
        let _ = writeln!(s, "|---|{}", "---:|".repeat(cols.len()));
        for row in &rows {
            let cells: Vec<String> = cols
                .iter()
                .map(|col| {
                    let found = r.cells.iter().find(|c| {
                        c.row.as_deref() == Some(row)
                            && c.column.as_deref() == Some(col)
                            && c.seeds > 0
                            && sec.seeds.contains_key(&c.id)
                    });
                    let Some(c) = found else { return "-".to_string() };
                    let mean = c.normalised_stats.as_ref().map(|st| st.mean);
                    let mean = mean.or(c.ours_normalised.map(|st| st.mean));
                    let noise = c.eval_noise.map_or(String::new(), |n| {
                        format!("; noise {:.1} over {} repeats", n.sd, n.repeats)
                    });
                    let seeds = if c.seeds == 1 { "seed" } else { "seeds" };
                    format!("{} ({} {seeds}{noise})", opt(mean), c.seeds)
                })
                .collect();
            let _ = writeln!(s, "| {row} | {} |", cells.join(" | "));
        }
        let _ = writeln!(s);
    }
    if s.is_empty() {
        s.push_str("No prompt-control run is archived yet.\n\n");
    }
    s.push_str(
        "Generated by `promptdt results render` from `results/`; raw returns, intervals, devices \
         and the claims' verdicts are in [RESULTS.md](../RESULTS.md) (\"Prompt control\", \"What \
         reproduces\").\n",
    );
    s
}

/// `doc` with the text between `begin` and `end` replaced by `block`; an error names the markers.
pub fn splice_block(doc: &str, begin: &str, end: &str, block: &str) -> Result<String, ReproError> {
    let missing = || ReproError::Invalid(format!("no {begin} ... {end} block"));
    let start = doc.find(begin).ok_or_else(missing)? + begin.len();
    let stop = doc[start..].find(end).ok_or_else(missing)? + start;
    Ok(format!("{}\n{block}{}", &doc[..start], &doc[stop..]))
}

/// A user experiment's section, after the paper's: its manifest, title and description, then per
/// budget its table and its claims' verdicts, by the code the paper's experiments' use.
fn user_section(s: &mut String, u: &UserExperiment) {
    let m = &u.m;
    let _ = writeln!(s, "\n## {} — user experiment `{}`\n", m.title.trim(), m.name);
    // A relative path is from the registry's directory, where RESULTS.md lies: a link from it.
    let file = match Path::new(&u.manifest).is_absolute() {
        true => format!("`{}`", u.manifest),
        false => format!("[`{0}`]({0})", u.manifest),
    };
    let _ = writeln!(
        s,
        "A user's experiment ([docs/reproduce.md](docs/reproduce.md#your-own-experiments)), read \
         from its manifest {file}, which its archived runs record: `promptdt reproduce {} --budget \
         B --report-only` writes its report, curves, `cells.csv`, `curves.csv` and `report.json` \
         from the registry.\n",
        u.manifest
    );
    let _ = writeln!(s, "{}\n", m.description.trim());
    for sec in &u.sections {
        cells_table(s, sec, &format!("### `{}` budget", sec.report.budget));
    }
    let _ = writeln!(
        s,
        "Its claims, judged by the rule the paper's are (\"What reproduces\"; fewer than {} seeds \
         on a side: provisional):\n",
        stats::MIN_SEEDS
    );
    for sec in &u.sections {
        verdicts(s, sec);
    }
}

/// A registry section's table under `heading`: one row per archived cell.
fn cells_table(s: &mut String, sec: &Section, heading: &str) {
    let r = &sec.report;
    let _ = writeln!(s, "{heading}\n");
    let _ = writeln!(s, "Budget (the plan): {}\n", r.budget_note.trim());
    let _ = writeln!(s, "{}\n", archive::text(&sec.planned, &sec.seeds, &sec.walls));
    // Evaluation noise beside seed noise: in the prompt-control table (whose rows differ by
    // evaluation alone), and wherever a cell's runs were evaluated with repeats.
    let noise = r.experiment == NOISE_EXPERIMENT || r.cells.iter().any(|c| c.eval_noise.is_some());
    let (noise_head, noise_rule) = if noise { (" evaluation noise |", "---:|") } else { ("", "") };
    // The paper's columns only where a cell has the paper's value (not in a user's experiment).
    let paper = report::has_paper(r);
    let (paper_head, paper_rule) =
        if paper { (" paper | paper normalised |", "---:|---:|") } else { ("", "") };
    let _ = writeln!(
        s,
        "| cell | budget | seeds | iterations | device | ours | ours normalised |{noise_head} \
         {:.0} % interval | IQM | ours, ratio of means |{paper_head}",
        100.0 * stats::CONFIDENCE
    );
    let _ = writeln!(s, "|---|---|---|---:|---|---:|---:|{noise_rule}---:|---:|---:|{paper_rule}");
    for c in &r.cells {
        let Some(seeds) = sec.seeds.get(&c.id).filter(|_| c.seeds > 0) else { continue };
        let ours = match c.success {
            Some(sr) => format!("{}, success {}", stat(c.ours, 1), stat(Some(sr), 2)),
            None => stat(c.ours, 1),
        };
        let report::PaperText { raw: p, normalised: pn } = report::PaperText::of(c);
        let paper_cells = if paper { format!(" {p} | {pn} |") } else { String::new() };
        let devices = sec.devices.get(&c.id).map(|d| d.iter().cloned().collect::<Vec<_>>());
        let devices = devices.map_or("-".into(), |d| d.join(", "));
        let (norm, ci, iqm) = normalised_text(c);
        let norm = match noise {
            true => format!("{norm} | {}", report::eval_noise_text(c)),
            false => norm,
        };
        let _ = writeln!(
            s,
            "| {} `{}` | {} | {} | {} | {} | {ours} | {norm} | {ci} | {iqm} | {} |{paper_cells}",
            c.label,
            c.id,
            r.budget,
            seeds_text(seeds),
            c.iteration.map_or("-".into(), |i| i.to_string()),
            devices,
            stat(c.ours_normalised_rom, 1),
        );
    }
    let _ = writeln!(s);
}

/// A registry section's verdicts: the claims measured (holds first), then each cell against the
/// paper's value where the paper's can be normalised, then how many claims were not measured.
fn verdicts(s: &mut String, sec: &Section) {
    let r = &sec.report;
    let measured: Vec<_> = r.claims.iter().filter(|c| c.verdict != "not measured").collect();
    let unmeasured = r.claims.len() - measured.len();
    let _ = writeln!(s, "- **{} (`{}`)**:", r.experiment, r.budget);
    let order = |v: &str| match v {
        "holds" => 0,
        "fails" => 1,
        "undecided" => 2,
        _ => 3,
    };
    let mut measured = measured;
    measured.sort_by_key(|c| order(&c.verdict));
    for c in &measured {
        let _ = writeln!(s, "  - {}: {} ({})", c.verdict, c.text, c.detail);
    }
    // Ours against the paper's value, normalised alike (ratio of means over the test tasks),
    // where the paper's can be normalised.
    for c in r.cells.iter().filter(|c| sec.seeds.contains_key(&c.id) && c.seeds > 0) {
        let (Some(o), Some(p)) = (c.ours_normalised_rom, c.paper_normalised) else { continue };
        let gap = o.mean - p;
        let how = if gap.abs() <= report::DEFAULT_MARGIN {
            format!("within {} normalised points of the paper", report::DEFAULT_MARGIN)
        } else if gap < 0.0 {
            "below the paper".into()
        } else {
            "above the paper".into()
        };
        let at = c.iteration.map_or(String::new(), |i| format!(", ours at iteration {i}"));
        // Below the paper: whether the run was still improving when its budget ended.
        let trend = match gap < -report::DEFAULT_MARGIN {
            true => trend(&c.curve).map_or(String::new(), |t| format!("; {t}")),
            false => String::new(),
        };
        let _ = writeln!(
            s,
            "  - {how}: {} `{}`, {:.1} (ratio of means; per-task mean of ratios {}) vs the \
             paper's {p:.1} at the paper's budget{at} ({} seed{}){trend}",
            c.label,
            c.id,
            o.mean,
            opt(c.ours_normalised.map(|x| x.mean)),
            o.n,
            if o.n == 1 { "" } else { "s" }
        );
    }
    if unmeasured > 0 {
        let _ = writeln!(
            s,
            "  - not measured: {unmeasured} of {} claims (their cells have no archived run)",
            r.claims.len()
        );
    }
}

/// The last three evaluations of a cell's curve (mean test return over seeds) and which way they
/// go: a cell below the paper that is still rising when its budget ends was cut short, one that
/// is flat or falling was not.
fn trend(curve: &[(u64, f64, f64)]) -> Option<String> {
    let last = &curve[curve.len().saturating_sub(3)..];
    if last.len() < 2 {
        return None;
    }
    let steps: Vec<f64> = last.windows(2).map(|w| w[1].1 - w[0].1).collect();
    let way = if steps.iter().all(|d| *d > 0.0) {
        "still rising when the budget ends"
    } else if steps.iter().all(|d| *d < 0.0) {
        "falling"
    } else {
        "neither rising nor falling"
    };
    let points: Vec<String> = last.iter().map(|(i, m, _)| format!("{m:.1} at {i}")).collect();
    Some(format!("mean test return over its last evaluations {}: {way}", points.join(", ")))
}

/// The README's few headline numbers: Figure 2's archived cells, normalised.
fn headline(sections: &[Section]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Figure 2 from the archived runs (normalised: 100 = expert data, 0 = random; generated by \
         `promptdt results render`; every row and the claims in [RESULTS.md](RESULTS.md)). \
         *ours normalised*: the per-task mean of ratios, mean ± sample SD over seeds; *ours, ratio \
         of means*: normalised the paper's way, the one compared with *paper normalised*:\n"
    );
    let _ = writeln!(
        s,
        "| cell | budget | seeds | iterations | ours normalised | ours, ratio of means | paper \
         normalised |"
    );
    let _ = writeln!(s, "|---|---|---|---:|---:|---:|---:|");
    let mut any = false;
    for sec in sections.iter().filter(|x| x.report.experiment == HEADLINE_EXPERIMENT) {
        for c in &sec.report.cells {
            let Some(seeds) = sec.seeds.get(&c.id).filter(|_| c.seeds > 0) else { continue };
            any = true;
            let _ = writeln!(
                s,
                "| {} `{}` | {} | {} | {} | {} | {} | {} |",
                c.label,
                c.id,
                sec.report.budget,
                seeds.len(),
                c.iteration.map_or("-".into(), |i| i.to_string()),
                normalised_text(c).0,
                stat(c.ours_normalised_rom, 1),
                report::PaperText::of(c).normalised
            );
        }
    }
    if !any {
        let _ = writeln!(s, "| (no archived run) | | | | | | |");
    }
    s
}

/// `readme` with its block between [`README_BEGIN`] and [`README_END`] replaced by `block`.
pub fn splice_readme(readme: &str, block: &str) -> Result<String, ReproError> {
    let missing =
        || ReproError::Invalid(format!("README has no {README_BEGIN} ... {README_END} block"));
    let start = readme.find(README_BEGIN).ok_or_else(missing)? + README_BEGIN.len();
    let end = readme[start..].find(README_END).ok_or_else(missing)? + start;
    Ok(format!("{}\n{block}{}", &readme[..start], &readme[end..]))
}

/// `promptdt results render`.
#[derive(Debug, Clone)]
pub struct RenderOptions {
    pub registry: PathBuf,
    pub results_md: PathBuf,
    /// The README whose block is rewritten; `None`: none.
    pub readme: Option<PathBuf>,
    /// docs/prompt-control.md, whose generated table is rewritten where the file exists; `None`:
    /// none.
    pub prompt_control_doc: Option<PathBuf>,
}

/// Writes `RESULTS.md` and the README block (atomically). Returns the files written.
pub fn write(o: &RenderOptions) -> Result<Vec<PathBuf>, ReproError> {
    let r = render(&o.registry)?;
    let io = |p: &Path, e: std::io::Error| ReproError::Io { path: p.to_path_buf(), source: e };
    pdt_base::fs::write_atomic(&o.results_md, r.results_md.as_bytes())
        .map_err(|e| io(&o.results_md, e))?;
    let mut files = vec![o.results_md.clone()];
    if let Some(readme) = &o.readme {
        let text = std::fs::read_to_string(readme).map_err(|e| io(readme, e))?;
        let new = splice_readme(&text, &r.readme_block)?;
        pdt_base::fs::write_atomic(readme, new.as_bytes()).map_err(|e| io(readme, e))?;
        files.push(readme.clone());
    }
    if let Some(doc) = o.prompt_control_doc.as_ref().filter(|d| d.is_file()) {
        let text = std::fs::read_to_string(doc).map_err(|e| io(doc, e))?;
        let new =
            splice_block(&text, PROMPT_CONTROL_BEGIN, PROMPT_CONTROL_END, &r.prompt_control_block)
                .map_err(|e| ReproError::Invalid(format!("{}: {e}", doc.display())))?;
        pdt_base::fs::write_atomic(doc, new.as_bytes()).map_err(|e| io(doc, e))?;
        files.push(doc.clone());
    }
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::trend;

    #[test]
    fn trend_names_the_way_the_last_three_evaluations_go() {
        let c = |v: &[f64]| -> Vec<(u64, f64, f64)> {
            v.iter().enumerate().map(|(i, m)| (100 * i as u64 + 1, *m, 0.0)).collect()
        };
        assert_eq!(trend(&c(&[1.0])), None);
        let rising = trend(&c(&[0.0, -9.0, -5.0, -1.0])).unwrap();
        assert_eq!(
            rising,
            "mean test return over its last evaluations -9.0 at 101, -5.0 at 201, -1.0 at 301: \
             still rising when the budget ends"
        );
        assert!(trend(&c(&[3.0, 2.0, 1.0])).unwrap().ends_with(": falling"));
        assert!(trend(&c(&[1.0, 3.0, 2.0])).unwrap().ends_with("neither rising nor falling"));
    }
}
