//! Why MT-ORL's test return rises and then falls, measured on the archived runs.
//!
//! A model without a prompt cannot tell the test tasks apart. If it acts the same on every task,
//! its return on a task is a fixed function of that task's goal, and the archived per-task test
//! returns show whether it does:
//! - a *direction* family (every task's features a unit vector: a goal direction), walking at one
//!   heading `phi` with one speed gives `R = a + b cos(goal - phi)`, linear in the features
//!   (`a + p f0 + q f1`), fitted by least squares;
//! - a *target-value* family (one feature: a target velocity), running at one speed `v*` gives
//!   `R = c - k |v - v*|`, fitted by a grid over `v*` with least squares for `(c, k)` at each.
//!   The grid spans every target of the run's split, training and test (a policy that imitates the
//!   training data may run at any speed the data has, beyond the test targets), and a fit on the
//!   grid's edge says so: its speed is then not identified.
//!
//! A small residual (against the spread of the returns) says the policy ignores the task. The
//! table lists it per evaluated iteration of each archived MT-ORL run, and Prompt-DT's last
//! iteration beside it as the contrast (a prompted policy should fit badly: it acts per task).
//! Families whose features are neither are skipped.

use crate::registry;
use crate::ReproError;
use pdt_rundir::RunDir;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

/// What a task-blind policy's return is, as a function of the task's goal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Fit {
    /// `R = a + b cos(goal - phi)`: one heading `phi` (degrees) for every task.
    Direction { offset: f64, amplitude: f64, heading_deg: f64 },
    /// `R = c - k |v - v*|`: one speed `v*` for every task.
    /// `k` is about the horizon for a policy that holds `v*` all episode (the reward loses
    /// `|v - target|` per step).
    /// `on_edge`: fewer than two test targets lie beyond `v*` on one side, so the kink rests on
    /// one return or none: not identified. Past the last test target every speed fits alike
    /// (`|v - v*|` is then linear in `v`, `c` absorbs the rest); such a fit is reported at that
    /// target.
    Target { value: f64, slope: f64, offset: f64, on_edge: bool },
}

/// One evaluation of one run, fitted.
#[derive(Debug, Clone, PartialEq)]
pub struct BlindFit {
    pub iteration: u64,
    pub mean_return: f64,
    pub fit: Fit,
    /// Root-mean-square residual of the fit over the test tasks.
    pub rmse: f64,
    /// Largest minus smallest test-task return.
    pub span: f64,
}

/// Least squares of `y` on the columns of `x` (rows = observations), by the normal equations
/// solved with Gaussian elimination (at most 3 unknowns here). `None` when singular.
fn least_squares(x: &[Vec<f64>], y: &[f64]) -> Option<Vec<f64>> {
    let n = x.first()?.len();
    let mut a = vec![vec![0.0; n + 1]; n];
    for (row, &yi) in x.iter().zip(y) {
        for i in 0..n {
            for j in 0..n {
                a[i][j] += row[i] * row[j];
            }
            a[i][n] += row[i] * yi;
        }
    }
    for col in 0..n {
        let pivot = (col..n).max_by(|&p, &q| a[p][col].abs().total_cmp(&a[q][col].abs()))?;
        if a[pivot][col].abs() < 1e-12 {
            return None;
        }
        a.swap(col, pivot);
        let pivot_row = a[col].clone();
        for (r, row) in a.iter_mut().enumerate() {
            if r != col {
                let f = row[col] / pivot_row[col];
                for (x, p) in row.iter_mut().zip(&pivot_row).skip(col) {
                    *x -= f * p;
                }
            }
        }
    }
    Some((0..n).map(|i| a[i][n] / a[i][i]).collect())
}

fn rmse(pred: impl Iterator<Item = f64>, y: &[f64]) -> f64 {
    let s: f64 = pred.zip(y).map(|(p, t)| (p - t).powi(2)).sum();
    (s / y.len().max(1) as f64).sqrt()
}

/// Fits a task-blind policy to per-task returns `y` given each task's `features`; a target-value
/// family's speed is searched over `range` widened to the tasks' own targets (`range`: every
/// target of the split, training tasks included). `None` when the features are of neither kind or
/// the tasks are too few (fewer than unknowns + 1).
pub fn fit(features: &[Vec<f64>], y: &[f64], range: Option<(f64, f64)>) -> Option<(Fit, f64)> {
    let unit =
        |f: &Vec<f64>| f.len() == 2 && ((f[0].powi(2) + f[1].powi(2)).sqrt() - 1.0).abs() < 1e-3;
    if features.len() >= 4 && features.iter().all(unit) {
        let x: Vec<Vec<f64>> = features.iter().map(|f| vec![1.0, f[0], f[1]]).collect();
        let w = least_squares(&x, y)?;
        let r = rmse(x.iter().map(|row| row.iter().zip(&w).map(|(a, b)| a * b).sum()), y);
        let fit = Fit::Direction {
            offset: w[0],
            amplitude: w[1].hypot(w[2]),
            heading_deg: w[2].atan2(w[1]).to_degrees().rem_euclid(360.0),
        };
        return Some((fit, r));
    }
    if features.len() >= 4 && features.iter().all(|f| f.len() == 1) {
        let v: Vec<f64> = features.iter().map(|f| f[0]).collect();
        let (r_lo, r_hi) = range.unwrap_or((f64::INFINITY, f64::NEG_INFINITY));
        let lo = v.iter().copied().fold(r_lo, f64::min);
        let hi = v.iter().copied().fold(r_hi, f64::max);
        // One speed among the split's targets (a policy that imitates the data runs at a speed
        // the data has).
        const STEPS: usize = 1000;
        let mut best: Option<(Fit, f64)> = None;
        for i in 0..=STEPS {
            let vs = lo + (hi - lo) * i as f64 / STEPS as f64;
            let x: Vec<Vec<f64>> = v.iter().map(|&t| vec![1.0, -(t - vs).abs()]).collect();
            let Some(mut w) = least_squares(&x, y) else { continue };
            if w[1] < 0.0 {
                // Running at one speed can only lose return away from it: k >= 0, so a task-aware
                // policy's returns are not fitted by an upside-down V.
                w = vec![y.iter().sum::<f64>() / y.len() as f64, 0.0];
            }
            let r = rmse(x.iter().map(|row| w[0] + w[1] * row[1]), y);
            if best.is_none_or(|(_, b)| r < b) {
                best =
                    Some((Fit::Target { value: vs, slope: w[1], offset: w[0], on_edge: false }, r));
            }
        }
        // At or past a test target's extreme the fit is flat in `v*`: report the extreme itself
        // (whichever speed past it rounding picked). Either way, a kink with fewer than two test
        // targets beyond it on one side rests on one return (or none): flagged, not identified.
        let (t_lo, t_hi) = (
            v.iter().copied().fold(f64::INFINITY, f64::min),
            v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        );
        let step = (hi - lo) / STEPS as f64;
        if let Some((Fit::Target { value, slope, offset, .. }, r)) = best {
            let snapped = match value {
                x if x >= t_hi - step / 2.0 => Some(t_hi),
                x if x <= t_lo + step / 2.0 => Some(t_lo),
                _ => None,
            };
            let (value, slope, offset, r) = match snapped {
                Some(e) => {
                    let x: Vec<Vec<f64>> = v.iter().map(|&t| vec![1.0, -(t - e).abs()]).collect();
                    let mut w = least_squares(&x, y)?;
                    if w[1] < 0.0 {
                        w = vec![y.iter().sum::<f64>() / y.len() as f64, 0.0];
                    }
                    let r = rmse(x.iter().map(|row| w[0] + w[1] * row[1]), y);
                    (e, w[1], w[0], r)
                }
                None => (value, slope, offset, r),
            };
            let above = v.iter().filter(|t| **t > value + step / 2.0).count();
            let below = v.iter().filter(|t| **t < value - step / 2.0).count();
            let on_edge = above.min(below) < 2;
            return Some((Fit::Target { value, slope, offset, on_edge }, r));
        }
        return best;
    }
    None
}

/// The run's family, as the table names it.
struct Family {
    name: String,
    horizon: usize,
}

/// Every evaluated iteration of the archived run at `key`, fitted (test tasks only).
fn fits_of(registry: &Path, key: &str) -> Result<Option<(Family, Vec<BlindFit>)>, ReproError> {
    let run = RunDir::open(registry.join(key))?;
    let info = run.info()?;
    let Ok(family) = pdt_envs::family(&info.env) else { return Ok(None) };
    let rows = run.eval_lines()?.map(|l| l.rows).unwrap_or_default();
    let mut by_iteration: BTreeMap<u64, BTreeMap<usize, f64>> = BTreeMap::new();
    for r in rows.iter().filter(|r| r.eval_on == "test" && r.return_mean.is_finite()) {
        by_iteration.entry(r.iteration).or_default().insert(r.task_index, r.return_mean);
    }
    // The speed grid's range: every target of the run's split (training and test tasks).
    let range = family.split(&info.task_split).ok().and_then(|(train, test)| {
        let v: Vec<f64> = train
            .iter()
            .chain(&test)
            .filter_map(|t| family.task_features(*t).ok())
            .filter(|f| f.len() == 1)
            .map(|f| f64::from(f[0]))
            .collect();
        let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        (lo <= hi).then_some((lo, hi))
    });
    let mut out = Vec::new();
    for (iteration, tasks) in by_iteration {
        let mut features = Vec::new();
        for &t in tasks.keys() {
            // A family without task features (no goal to fit against) is skipped.
            let Ok(f) = family.task_features(t) else { return Ok(None) };
            features.push(f.into_iter().map(f64::from).collect::<Vec<f64>>());
        }
        let y: Vec<f64> = tasks.values().copied().collect();
        let Some((fit, rmse)) = fit(&features, &y, range) else { return Ok(None) };
        let span = y.iter().copied().fold(f64::NEG_INFINITY, f64::max)
            - y.iter().copied().fold(f64::INFINITY, f64::min);
        let mean_return = y.iter().sum::<f64>() / y.len() as f64;
        out.push(BlindFit { iteration, mean_return, fit, rmse, span });
    }
    Ok(Some((Family { name: info.env, horizon: family.preset().horizon }, out)))
}

fn describe(f: &Fit, horizon: usize) -> String {
    match *f {
        Fit::Direction { offset, amplitude, heading_deg } => {
            format!("one heading {heading_deg:.0}°: R = {offset:.0} + {amplitude:.0} cos(goal - {heading_deg:.0}°)")
        }
        Fit::Target { value, slope, offset, on_edge } => {
            let edge = match on_edge {
                true => {
                    "; fewer than two test targets lie beyond the speed on one side, so \
                         the fit does not pin it down: not identified"
                }
                false => "",
            };
            format!(
                "one speed {value:.2}: R = {offset:.0} - {slope:.0} \\|v - {value:.2}\\| \
                 (k = {slope:.0} of a horizon {horizon}{edge})"
            )
        }
    }
}

/// The `RESULTS.md` section: a table of the fits, or `None` when no archived MT-ORL run has a
/// family of either kind.
pub fn section(registry: &Path) -> Result<Option<String>, ReproError> {
    let keys = registry::keys(registry);
    let mut rows = String::new();
    let mut bullets = String::new();
    for key in keys.iter().filter(|k| k.split('/').nth(1) == Some("mt-orl")) {
        let Some((env, fits)) = fits_of(registry, key)? else { continue };
        let peak = fits.iter().max_by(|a, b| a.mean_return.total_cmp(&b.mean_return));
        if let (Some(p), Some(l)) = (peak, fits.last()) {
            let _ = writeln!(
                bullets,
                "- `{key}`: best mean test return {:.1} at iteration {} (fit residual {:.1} of a \
                 span {:.1}), then {:.1} at iteration {}: {} (residual {:.1} of a span {:.1}).",
                p.mean_return,
                p.iteration,
                p.rmse,
                p.span,
                l.mean_return,
                l.iteration,
                describe(&l.fit, env.horizon),
                l.rmse,
                l.span
            );
        }
        for f in &fits {
            let _ = writeln!(
                rows,
                "| `{key}` | {} | {} | {:.1} | {} | {:.1} | {:.1} |",
                env.name,
                f.iteration,
                f.mean_return,
                describe(&f.fit, env.horizon),
                f.rmse,
                f.span
            );
        }
        // The contrast: the same family's Prompt-DT runs at their last evaluation.
        let prefix = key.split('/').next().unwrap_or_default();
        let seed = key.rsplit('/').next().unwrap_or_default();
        let budget = key.split('/').nth(2).unwrap_or_default();
        let pdt = format!("{prefix}/prompt-dt/{budget}/{seed}");
        if keys.contains(&pdt) {
            if let Some((env, fits)) = fits_of(registry, &pdt)? {
                if let Some(f) = fits.last() {
                    let _ = writeln!(
                        rows,
                        "| `{pdt}` (contrast) | {} | {} | {:.1} | {} | {:.1} | {:.1} |",
                        env.name,
                        f.iteration,
                        f.mean_return,
                        describe(&f.fit, env.horizon),
                        f.rmse,
                        f.span
                    );
                }
            }
        }
    }
    if rows.is_empty() {
        return Ok(None);
    }
    let mut s = String::new();
    let _ = writeln!(
        s,
        "The test returns of a policy that acts the same on every task are a fixed function of \
         each task's goal: for a heading `phi`, `R = a + b cos(goal - phi)`; for a speed `v*`, \
         `R = c - k |v - v*|`. Each evaluated iteration of each archived MT-ORL run is fitted by \
         that function over its test tasks (`crates/repro/src/task_blind.rs`; a speed is searched \
         over every target of the run's split, training tasks included, and a speed with fewer \
         than two test targets beyond it on one side is marked not identified). A residual (rmse) \
         far below the returns' span means the policy ignores the task; Prompt-DT's last \
         evaluation of the same seed is the contrast.\n"
    );
    let _ = writeln!(
        s,
        "| run | env | iteration | mean test return | task-blind fit | rmse | span of task returns |"
    );
    let _ = writeln!(s, "|---|---|---:|---:|---|---:|---:|");
    s.push_str(&rows);
    let _ = writeln!(s, "\nPer MT-ORL run, its best evaluation and its last:\n");
    s.push_str(&bullets);
    Ok(Some(s))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_policy_with_one_heading_is_found() {
        let goals = [0.25_f64, 1.8, 0.9, 3.6, 4.1];
        let features: Vec<Vec<f64>> = goals.iter().map(|g| vec![g.cos(), g.sin()]).collect();
        let phi = 300_f64.to_radians();
        let y: Vec<f64> = goals.iter().map(|g| 40.0 + 500.0 * (g - phi).cos()).collect();
        let (f, r) = fit(&features, &y, None).expect("fit");
        let Fit::Direction { offset, amplitude, heading_deg } = f else { panic!("{f:?}") };
        assert!(r < 1e-6 && (offset - 40.0).abs() < 1e-6 && (amplitude - 500.0).abs() < 1e-6);
        assert!((heading_deg - 300.0).abs() < 1e-6, "{heading_deg}");
    }

    #[test]
    fn a_policy_with_one_speed_is_found_and_a_task_aware_one_fits_badly() {
        let v = [0.22_f64, 0.6, 1.2, 1.8, 2.02];
        let features: Vec<Vec<f64>> = v.iter().map(|&t| vec![t]).collect();
        let y: Vec<f64> = v.iter().map(|t| -30.0 - 200.0 * (t - 0.95).abs()).collect();
        let (f, r) = fit(&features, &y, Some((0.0, 3.0))).expect("fit");
        let Fit::Target { value, slope, on_edge, .. } = f else { panic!("{f:?}") };
        assert!((value - 0.95).abs() < 0.01 && (slope - 200.0).abs() < 5.0 && r < 2.0, "{f:?} {r}");
        assert!(!on_edge, "{f:?}");
        // 1.95: one test target above it, so its kink rests on one return.
        let y: Vec<f64> = v.iter().map(|t| -30.0 - 200.0 * (t - 1.95).abs()).collect();
        let (f, _) = fit(&features, &y, Some((0.0, 3.0))).expect("fit");
        let Fit::Target { value, on_edge, .. } = f else { panic!("{f:?}") };
        assert!((value - 1.95).abs() < 0.01 && on_edge, "{f:?}");
        // A speed beyond the test targets (2.8, inside the searched range) fits exactly, but so
        // does every speed past 2.02: the fit is flagged at the test targets' end, not identified.
        let y: Vec<f64> = v.iter().map(|t| -30.0 - 200.0 * (t - 2.8).abs()).collect();
        for range in [Some((0.0, 3.0)), None] {
            let (f, r) = fit(&features, &y, range).expect("fit");
            let Fit::Target { value, on_edge, .. } = f else { panic!("{f:?}") };
            assert!((value - 2.02).abs() < 1e-9 && on_edge && r < 1e-6, "{f:?} {r}");
            assert!(describe(&f, 200).contains("not identified"), "{}", describe(&f, 200));
        }
        // A policy that tracks each target loses a constant amount: no one speed explains the
        // returns... except a flat one (k = 0), whose residual is 0 too; so use returns that vary.
        let y: Vec<f64> = [-45.0, -120.0, -60.0, -150.0, -50.0].to_vec();
        let (_, r) = fit(&features, &y, None).expect("fit");
        assert!(r > 20.0, "{r}");
    }
}
