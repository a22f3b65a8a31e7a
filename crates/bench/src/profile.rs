//! `bench --profile`: what one iteration of a case runs, counted by libtorch's profiler
//! (`pdt_torch::profiler`): host operators and, on CUDA, kernels, copies and runtime calls, with
//! where their time goes. Issue 30 asks where a step's time goes (kernels per step) on the GPU,
//! which no profiler on those machines could say.
//!
//! A case's function builds its inputs (a model, a pack, batches) before it times its iterations,
//! so one profiled call counts that set-up too. Each case is therefore profiled twice, with
//! [`SHORT`] and [`LONG`] timed iterations after one warm-up: the set-up is the same in both, and
//! the difference divided by `LONG - SHORT` is one iteration's own (exact for counts, since every
//! iteration runs the same operators; durations are the profiled runs' own, slower than unprofiled
//! ones).

use crate::{BenchConfig, BenchError, CaseTiming, EngineReport};
use pdt_torch::profiler::{self, Event, EventKind};
use serde::Serialize;
use std::collections::BTreeMap;

const SHORT: usize = 2;
const LONG: usize = 4;
/// Entries listed per kind.
const TOP: usize = 8;

/// One iteration of a case, as the profiler saw it.
#[derive(Debug, Clone, Serialize)]
pub struct CaseProfile {
    pub case: String,
    /// Host operators dispatched per iteration (nested ones included).
    pub ops: f64,
    /// CUDA kernels launched per iteration (0 on the CPU).
    pub kernels: f64,
    /// CUDA copies and memsets per iteration.
    pub copies: f64,
    /// The operators and kernels that take the most time per iteration, by kind.
    pub top: Vec<ProfiledName>,
    /// Every operator and kernel name of an iteration, the costliest first (in `bench.json` only:
    /// where a step's operators come from, to compare one case's mix with another's).
    pub names: Vec<ProfiledName>,
}

/// What one iteration runs, as counted for the PyTorch baseline (`bench_torch.py --profile`, the
/// same difference of 4 and 2 iterations).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct OpCounts {
    pub ops: f64,
    pub kernels: f64,
    pub copies: f64,
}

/// One operator or kernel name's share of an iteration.
#[derive(Debug, Clone, Serialize)]
pub struct ProfiledName {
    pub name: String,
    pub kind: EventKind,
    pub per_iteration: f64,
    /// Milliseconds per iteration (an operator's time includes the operators it calls).
    pub ms: f64,
}

/// Count and total nanoseconds per (kind, name).
type Tally = BTreeMap<(EventKind, String), (u64, u64)>;

fn tally(events: Vec<Event>) -> Tally {
    let mut t = Tally::new();
    for e in events {
        let entry = t.entry((e.kind, e.name)).or_default();
        entry.0 += 1;
        entry.1 += e.duration_ns;
    }
    t
}

/// Profiles `time` (a case's timing function, given the configuration to time with) as the module
/// docs say.
pub fn profile_case(
    case: &str,
    cfg: &BenchConfig,
    mut time: impl FnMut(&BenchConfig) -> Result<CaseTiming, BenchError>,
) -> Result<CaseProfile, BenchError> {
    let mut run = |iters: usize| -> Result<Tally, BenchError> {
        let short = BenchConfig { warmup: 1, iters, ..cfg.clone() };
        let p = profiler::start(cfg.device.is_cuda())?;
        time(&short)?;
        Ok(tally(p.stop()?))
    };
    let (a, b) = (run(SHORT)?, run(LONG)?);
    let steps = (LONG - SHORT) as f64;
    let mut names: Vec<ProfiledName> = Vec::new();
    for ((kind, name), &(n, ns)) in &b {
        let (n0, ns0) = a.get(&(*kind, name.clone())).copied().unwrap_or((0, 0));
        let per = (n as f64 - n0 as f64) / steps;
        if per > 0.0 {
            let ms = (ns as f64 - ns0 as f64).max(0.0) / steps / 1e6;
            names.push(ProfiledName { name: name.clone(), kind: *kind, per_iteration: per, ms });
        }
    }
    let count = |k: &[EventKind]| -> f64 {
        names.iter().filter(|p| k.contains(&p.kind)).fold(0.0, |s, p| s + p.per_iteration)
    };
    let (ops, kernels) = (count(&[EventKind::Op]), count(&[EventKind::Kernel]));
    let copies = count(&[EventKind::Memcpy, EventKind::Memset]);
    names.sort_by(|x, y| y.ms.total_cmp(&x.ms));
    let mut top = Vec::new();
    for kind in [EventKind::Kernel, EventKind::Op] {
        top.extend(names.iter().filter(|p| p.kind == kind).take(TOP).cloned());
    }
    Ok(CaseProfile { case: case.to_string(), ops, kernels, copies, top, names })
}

/// The profiles as Markdown: a line per case (with PyTorch's counts where its baseline ran the
/// case with `--profile`), then each case's costliest names.
pub fn render(profiles: &[CaseProfile], pytorch: Option<&EngineReport>) -> String {
    use pdt_base::table::{Rule, Table};
    if profiles.is_empty() {
        return String::new();
    }
    let header = [
        "case",
        "host ops per iteration",
        "CUDA kernels per iteration",
        "CUDA copies",
        "PyTorch: ops / kernels / copies",
    ];
    let mut t = Table::new(header.map(String::from).to_vec());
    for p in profiles {
        let theirs = pytorch
            .and_then(|r| r.results.iter().find(|c| c.name == p.case))
            .and_then(|c| c.profile)
            .map_or("-".into(), |c| format!("{:.0} / {:.0} / {:.0}", c.ops, c.kernels, c.copies));
        t.push(vec![
            p.case.clone(),
            format!("{:.0}", p.ops),
            format!("{:.0}", p.kernels),
            format!("{:.0}", p.copies),
            theirs,
        ]);
    }
    let mut s = format!(
        "\nProfiled (libtorch's profiler; per iteration, the difference of {LONG} and {SHORT} \
         iterations):\n\n{}",
        t.markdown(Rule::Tight)
    );
    for p in profiles {
        let mut t = Table::new(
            ["kind", "name", "per iteration", "ms per iteration (profiled)"]
                .map(String::from)
                .to_vec(),
        );
        for n in &p.top {
            let kind = match n.kind {
                EventKind::Kernel => "kernel",
                _ => "op (inclusive)",
            };
            // CUDA kernels' template names run to hundreds of characters.
            let name: String = match n.name.char_indices().nth(90) {
                Some((i, _)) => format!("{}...", &n.name[..i]),
                None => n.name.clone(),
            };
            t.push(vec![
                kind.into(),
                name,
                format!("{:.0}", n.per_iteration),
                format!("{:.3}", n.ms),
            ]);
        }
        s.push_str(&format!("\n`{}`:\n\n{}", p.case, t.markdown(Rule::Tight)));
    }
    s
}
