//! The statistics a report judges the paper's claims with (docs/reproduce.md#claims): per cell the
//! seeds' sample standard deviation, a 95 % interval by a stratified bootstrap over seeds and test
//! tasks, and the interquartile mean; per claim the bootstrap interval of the difference between
//! two cells, read against the claim's margin.
//!
//! The bootstrap is the hierarchical one `rliable` describes (Agarwal et al., NeurIPS 2021):
//! resample the seeds with replacement and, within each seed drawn, its test tasks with
//! replacement. It is seeded ([`SEED`]) and draws a fixed number of resamples ([`RESAMPLES`]), so
//! a report (and `RESULTS.md`, committed) is the same on every run and machine: the generator is
//! integer arithmetic (SplitMix64), the percentiles sorted f64s.

/// Resamples per interval: the percentile interval's Monte Carlo error at 10000 is a few hundredths
/// of the interval's width, well under the one decimal the reports print.
pub const RESAMPLES: usize = 10_000;
/// The generator's seed: fixed, so a regenerated report is byte for byte the same.
pub const SEED: u64 = 2021;
/// The interval's coverage.
pub const CONFIDENCE: f64 = 0.95;
/// Seeds a cell needs on each side before a claim on it can read anything but provisional: with
/// one seed the seed-to-seed variation is unmeasured, with two it is one difference.
pub const MIN_SEEDS: usize = 3;

/// A cell's scores: per seed, one score per test task (the last evaluation's normalised returns).
pub type Scores = [Vec<f64>];

/// SplitMix64 (Steele et al. 2014): a few integer operations, the same on every platform.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `0..n` (`n` is a count of seeds or tasks: the modulo's bias is below 1e-17).
    fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
}

/// A two-sided interval.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Interval {
    pub lo: f64,
    pub hi: f64,
}

impl std::fmt::Display for Interval {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "[{:.1}, {:.1}]", self.lo, self.hi)
    }
}

/// What a report shows of one cell's normalised scores.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct CellStats {
    pub seeds: usize,
    /// Mean over seeds of each seed's mean over its tasks.
    pub mean: f64,
    /// Sample standard deviation (n - 1) of the seeds' means; `None` for one seed.
    pub sd: Option<f64>,
    /// 95 % stratified-bootstrap interval of the mean.
    pub ci: Interval,
    /// Interquartile mean of the seeds' per-task scores pooled, where the cell has [`MIN_SEEDS`].
    pub iqm: Option<f64>,
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

/// Keeps the seeds that have a score on some task and only finite scores: a diverged seed's NaN is
/// left out, as `Stat` does.
fn clean(s: &Scores) -> Vec<Vec<f64>> {
    s.iter().filter(|t| !t.is_empty() && t.iter().all(|x| x.is_finite())).cloned().collect()
}

/// Sample standard deviation (n - 1); `None` for fewer than two values.
pub fn sample_sd(v: &[f64]) -> Option<f64> {
    if v.len() < 2 {
        return None;
    }
    let m = mean(v);
    Some((v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt())
}

/// Interquartile mean: the mean of the values left after cutting `floor(n / 4)` from each end of
/// the sorted values (`scipy.stats.trim_mean(x, 0.25)`, which `rliable` uses).
pub fn iqm(values: &[f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let cut = v.len() / 4;
    Some(mean(&v[cut..v.len() - cut]))
}

/// The `q` quantile of sorted values, linearly interpolated (numpy's default).
fn quantile(sorted: &[f64], q: f64) -> f64 {
    let pos = q * (sorted.len() - 1) as f64;
    let (i, frac) = (pos.floor() as usize, pos - pos.floor());
    match sorted.get(i + 1) {
        Some(next) => sorted[i] + frac * (next - sorted[i]),
        None => sorted[i],
    }
}

/// One bootstrap draw of a cell's mean: seeds with replacement, then each drawn seed's tasks with
/// replacement.
fn draw(s: &[Vec<f64>], rng: &mut Rng) -> f64 {
    let mut total = 0.0;
    for _ in 0..s.len() {
        let tasks = &s[rng.below(s.len())];
        let mut sum = 0.0;
        for _ in 0..tasks.len() {
            sum += tasks[rng.below(tasks.len())];
        }
        total += sum / tasks.len() as f64;
    }
    total / s.len() as f64
}

fn percentile_interval(mut draws: Vec<f64>) -> Interval {
    draws.sort_by(f64::total_cmp);
    let tail = (1.0 - CONFIDENCE) / 2.0;
    Interval { lo: quantile(&draws, tail), hi: quantile(&draws, 1.0 - tail) }
}

/// The 95 % percentile interval of `a`'s mean minus `b`'s (`b` empty: of `a`'s mean), `resamples`
/// draws of each from the generator seeded with `seed`. `None` where a side has no scores.
pub fn bootstrap(a: &Scores, b: Option<&Scores>, resamples: usize, seed: u64) -> Option<Interval> {
    let a = clean(a);
    let b = b.map(clean);
    if a.is_empty() || b.as_ref().is_some_and(Vec::is_empty) || resamples == 0 {
        return None;
    }
    let mut rng = Rng(seed);
    let draws = (0..resamples)
        .map(|_| {
            let x = draw(&a, &mut rng);
            x - b.as_ref().map_or(0.0, |b| draw(b, &mut rng))
        })
        .collect();
    Some(percentile_interval(draws))
}

/// A cell's statistics at the reports' settings; `None` where it has no scores.
pub fn cell_stats(s: &Scores) -> Option<CellStats> {
    let s = clean(s);
    let means: Vec<f64> = s.iter().map(|t| mean(t)).collect();
    let ci = bootstrap(&s, None, RESAMPLES, SEED)?;
    let pooled: Vec<f64> = s.iter().flatten().copied().collect();
    Some(CellStats {
        seeds: s.len(),
        mean: mean(&means),
        sd: sample_sd(&means),
        ci,
        iqm: if s.len() >= MIN_SEEDS { iqm(&pooled) } else { None },
    })
}

/// What the interval of a difference says about it against a threshold pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Call {
    Holds,
    Fails,
    Undecided,
}

impl Call {
    pub fn word(self) -> &'static str {
        match self {
            Call::Holds => "holds",
            Call::Fails => "fails",
            Call::Undecided => "undecided",
        }
    }
}

/// A judged claim: its verdict (`holds`, `fails`, `undecided`, or `provisional (n vs m seeds)`)
/// and the numbers behind it.
#[derive(Debug, Clone, PartialEq)]
pub struct Judgement {
    pub verdict: String,
    pub detail: String,
    /// What the intervals alone say (before the seed count makes it provisional).
    pub call: Call,
}

fn verdict(call: Call, seeds: &[usize]) -> String {
    match seeds.iter().any(|n| *n < MIN_SEEDS) {
        true => {
            let list: Vec<String> = seeds.iter().map(usize::to_string).collect();
            format!("provisional ({} seeds)", list.join(" vs "))
        }
        false => call.word().to_string(),
    }
}

fn interval_note() -> String {
    format!(
        "{:.0} % interval by a stratified bootstrap over seeds x tasks, {RESAMPLES} resamples",
        100.0 * CONFIDENCE
    )
}

/// "`a` beats `b` by more than `margin`": holds when the interval of `a - b` lies above the
/// margin, fails when it lies below it, undecided otherwise; provisional with fewer than
/// [`MIN_SEEDS`] seeds on a side, whatever the interval says (the detail says what it says).
pub fn judge_better(a: (&str, &Scores), b: (&str, &Scores), margin: f64) -> Option<Judgement> {
    let (sa, sb) = (cell_stats(a.1)?, cell_stats(b.1)?);
    let d = bootstrap(a.1, Some(b.1), RESAMPLES, SEED)?;
    let call = if d.lo > margin {
        Call::Holds
    } else if d.hi < margin {
        Call::Fails
    } else {
        Call::Undecided
    };
    let detail = format!(
        "{}: {:.1} ({} seed{}) vs {}: {:.1} ({} seed{}); a - b = {:.1}, {d} ({}); margin {margin}: {}",
        a.0,
        sa.mean,
        sa.seeds,
        plural(sa.seeds),
        b.0,
        sb.mean,
        sb.seeds,
        plural(sb.seeds),
        sa.mean - sb.mean,
        interval_note(),
        match call {
            Call::Holds => "the interval lies above it".to_string(),
            Call::Fails => "the interval lies below it".to_string(),
            Call::Undecided => "the interval contains it".to_string(),
        }
    );
    let verdict = verdict(call, &[sa.seeds, sb.seeds]);
    let detail = match verdict.starts_with("provisional") {
        true => format!("{detail} (with {MIN_SEEDS} seeds a side it would read {})", call.word()),
        false => detail,
    };
    Some(Judgement { verdict, detail, call })
}

/// "The cells perform similarly": an equivalence test. Holds when the interval of every pair's
/// difference lies inside `(-margin, margin)`, fails when some pair's lies wholly outside it,
/// undecided otherwise; provisional with fewer than [`MIN_SEEDS`] seeds in a cell.
pub fn judge_similar(cells: &[(&str, &Scores)], margin: f64) -> Option<Judgement> {
    let stats: Vec<CellStats> = cells.iter().map(|(_, s)| cell_stats(s)).collect::<Option<_>>()?;
    let mut call = Call::Holds;
    let mut pairs = Vec::new();
    for i in 0..cells.len() {
        for j in i + 1..cells.len() {
            let d = bootstrap(cells[i].1, Some(cells[j].1), RESAMPLES, SEED)?;
            if d.lo > margin || d.hi < -margin {
                call = Call::Fails;
            } else if (d.lo <= -margin || d.hi >= margin) && call == Call::Holds {
                call = Call::Undecided;
            }
            pairs.push(format!(
                "{} - {} = {:.1}, interval {d}",
                cells[i].0,
                cells[j].0,
                stats[i].mean - stats[j].mean
            ));
        }
    }
    let scores: Vec<String> = cells
        .iter()
        .zip(&stats)
        .map(|((id, _), s)| format!("{id}: {:.1} ({} seed{})", s.mean, s.seeds, plural(s.seeds)))
        .collect();
    let detail = format!(
        "{}; {} ({}); equivalence margin ±{margin}: {}",
        scores.join(", "),
        pairs.join("; "),
        interval_note(),
        match call {
            Call::Holds => "every interval lies inside it",
            Call::Fails => "an interval lies outside it",
            Call::Undecided => "an interval reaches beyond it",
        }
    );
    let seeds: Vec<usize> = stats.iter().map(|s| s.seeds).collect();
    let verdict = verdict(call, &seeds);
    let detail = match verdict.starts_with("provisional") {
        true => format!("{detail} (with {MIN_SEEDS} seeds a cell it would read {})", call.word()),
        false => detail,
    };
    Some(Judgement { verdict, detail, call })
}

fn plural(n: usize) -> &'static str {
    if n == 1 {
        ""
    } else {
        "s"
    }
}

/// The worked example of docs/reproduce.md#claims, computed by the rule itself (a test checks that
/// the doc quotes it): the 3-vs-3 data of [`example_scores`], judged as "a beats b" with margin 10.
pub fn worked_example() -> String {
    let (a, b) = example_scores();
    let mut s = String::new();
    let row = |name: &str, x: &[Vec<f64>]| {
        let st = cell_stats(x).expect("example scores");
        let seeds: Vec<String> = x
            .iter()
            .map(|t| {
                let v: Vec<String> = t.iter().map(|v| format!("{v:.1}")).collect();
                format!("({})", v.join(", "))
            })
            .collect();
        format!(
            "- {name}: per seed, its test tasks' scores {}; mean {:.2}, sample SD {:.2}, 95 % interval \
             {}, IQM {:.2}\n",
            seeds.join(" "),
            st.mean,
            st.sd.unwrap_or(0.0),
            st.ci,
            st.iqm.unwrap_or(f64::NAN)
        )
    };
    s.push_str(&row("a", &a));
    s.push_str(&row("b", &b));
    for margin in [10.0, 20.0] {
        let j = judge_better(("a", &a), ("b", &b), margin).expect("example scores");
        s.push_str(&format!("- \"a beats b\", margin {margin}: **{}**: {}\n", j.verdict, j.detail));
    }
    let j = judge_better(("a", &a[..1]), ("b", &b[..1]), 10.0).expect("example scores");
    s.push_str(&format!(
        "- the same with seed 1 alone on each side: **{}**: {}\n",
        j.verdict, j.detail
    ));
    let j = judge_similar(&[("a", &a), ("b", &b)], 10.0).expect("example scores");
    s.push_str(&format!(
        "- \"a and b perform similarly\", margin 10: **{}**: {}\n",
        j.verdict, j.detail
    ));
    s
}

/// The test data of the rule's 3-vs-3 case (and the docs' worked example): three seeds of two
/// test tasks each, `a` about 21 points above `b`. Two tasks keep the bootstrap's distribution
/// small enough for `crates/repro/tests/bootstrap_check.py` to enumerate exactly.
pub fn example_scores() -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    (
        vec![vec![74.0, 66.0], vec![80.0, 70.0], vec![71.0, 75.0]],
        vec![vec![52.0, 49.0], vec![58.0, 46.0], vec![55.0, 50.0]],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(v: f64) -> Vec<Vec<f64>> {
        vec![vec![v, v + 2.0, v - 2.0]]
    }

    #[test]
    fn one_seed_against_one_reads_provisional_however_large_the_lead() {
        let j = judge_better(("a", &one(90.0)), ("b", &one(10.0)), 10.0).unwrap();
        assert_eq!(j.verdict, "provisional (1 vs 1 seeds)", "{}", j.detail);
        assert_eq!(j.call, Call::Holds, "{}", j.detail);
        assert!(j.detail.contains("it would read holds"), "{}", j.detail);
        let (a, _) = example_scores();
        let j = judge_better(("a", &a), ("b", &one(10.0)), 10.0).unwrap();
        assert_eq!(j.verdict, "provisional (3 vs 1 seeds)", "{}", j.detail);
    }

    #[test]
    fn three_against_three_holds_above_the_margin_fails_below_and_is_undecided_across() {
        let (a, b) = example_scores();
        let d = bootstrap(&a, Some(&b), RESAMPLES, SEED).unwrap();
        assert!(d.lo > 10.0 && d.hi < 30.0, "{d:?}");
        assert_eq!(judge_better(("a", &a), ("b", &b), 10.0).unwrap().verdict, "holds");
        assert_eq!(judge_better(("a", &a), ("b", &b), 20.0).unwrap().verdict, "undecided");
        assert_eq!(judge_better(("a", &a), ("b", &b), 30.0).unwrap().verdict, "fails");
        assert_eq!(judge_better(("b", &b), ("a", &a), 10.0).unwrap().verdict, "fails");
        // The interval brackets the observed difference of means.
        let (sa, sb) = (cell_stats(&a).unwrap(), cell_stats(&b).unwrap());
        assert!(d.lo < sa.mean - sb.mean && sa.mean - sb.mean < d.hi);
    }

    #[test]
    fn similar_needs_the_interval_inside_the_margin_not_close_means() {
        // Close means but a large spread over seeds: not similar.
        let a = vec![vec![20.0, 22.0], vec![80.0, 78.0], vec![50.0, 52.0]];
        let b = vec![vec![75.0, 77.0], vec![25.0, 27.0], vec![48.0, 50.0]];
        let j = judge_similar(&[("a", &a), ("b", &b)], 10.0).unwrap();
        assert_eq!(j.verdict, "undecided", "{}", j.detail);
        // Tight and close: similar.
        let c = vec![vec![50.0, 51.0], vec![52.0, 50.0], vec![49.0, 51.0]];
        let d = vec![vec![51.0, 50.0], vec![50.0, 52.0], vec![50.0, 49.0]];
        assert_eq!(judge_similar(&[("c", &c), ("d", &d)], 10.0).unwrap().verdict, "holds");
        // Far apart: not similar, measured.
        let e: Vec<Vec<f64>> = c.iter().map(|t| t.iter().map(|x| x + 40.0).collect()).collect();
        assert_eq!(judge_similar(&[("c", &c), ("e", &e)], 10.0).unwrap().verdict, "fails");
        // One seed a side: provisional, however close.
        let j = judge_similar(&[("c", &c[..1]), ("d", &d[..1])], 10.0).unwrap();
        assert_eq!(j.verdict, "provisional (1 vs 1 seeds)", "{}", j.detail);
    }

    #[test]
    fn statistics_of_a_cell() {
        assert_eq!(sample_sd(&[1.0]), None);
        assert!((sample_sd(&[1.0, 2.0, 3.0]).unwrap() - 1.0).abs() < 1e-12);
        // 8 values: 2 cut from each end.
        assert_eq!(iqm(&[100.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, -100.0]), Some(3.5));
        let (a, _) = example_scores();
        let s = cell_stats(&a).unwrap();
        assert_eq!(s.seeds, 3);
        assert!((s.mean - 72.666_666_666_666_67).abs() < 1e-9);
        assert!(s.iqm.is_some());
        assert_eq!(cell_stats(&a[..2]).unwrap().iqm, None);
        // Deterministic: the same interval twice.
        assert_eq!(cell_stats(&a), cell_stats(&a));
        // A diverged seed is left out.
        let mut nan = a.clone();
        nan.push(vec![f64::NAN, 1.0]);
        assert_eq!(cell_stats(&nan).unwrap().seeds, 3);
        assert_eq!(quantile(&[0.0, 10.0], 0.25), 2.5);
    }
}
