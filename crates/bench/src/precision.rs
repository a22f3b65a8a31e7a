//! `--matmul bf16`'s part of the report: the bf16 timings beside the fp32 ones of the same run.

use crate::{BenchReport, EngineReport};
use pdt_base::table::{Rule, Table};

/// `--matmul bf16`'s second table: each case's bf16 and fp32 medians, both engines, and the
/// ratios the bf16 targets are stated in (docs/benchmarks.md).
pub(crate) fn render_bf16(r: &BenchReport, fp32: &BenchReport) -> String {
    let median = |e: Option<&EngineReport>, name: &str| {
        e.and_then(|e| e.results.iter().find(|t| t.name == name)).map(|t| t.median_ms)
    };
    let ms = |x: Option<f64>| x.map_or("not run".into(), |x| format!("{x:.2}"));
    let ratio = |a: Option<f64>, b: Option<f64>| match (a, b) {
        (Some(a), Some(b)) if b > 0.0 => format!("{:.2}x", a / b),
        _ => "-".into(),
    };
    let header = [
        "case",
        "promptdt bf16 ms",
        "promptdt fp32 ms",
        "promptdt fp32 / bf16",
        "PyTorch autocast bf16 ms",
        "PyTorch fp32 ms",
        "PyTorch bf16 / promptdt bf16",
    ];
    let mut t = Table::new(header.map(String::from).to_vec());
    for c in &r.promptdt.results {
        let ours = Some(c.median_ms);
        let ours32 = median(Some(&fp32.promptdt), &c.name);
        let theirs = median(r.pytorch.as_ref(), &c.name);
        let theirs32 = median(fp32.pytorch.as_ref(), &c.name);
        t.push(vec![
            c.name.clone(),
            ms(ours),
            ms(ours32),
            ratio(ours32, ours),
            ms(theirs),
            ms(theirs32),
            ratio(theirs, ours),
        ]);
    }
    let mut s = String::from("\nbf16 beside fp32 (medians of the same run):\n\n");
    s += &t.markdown(Rule::Tight);
    if r.bf16_emulated {
        s.push_str(
            "\nbf16 here is emulated (PROMPTDT_BF16_EMULATED=1: this hardware has no native bf16): \
             these timings say nothing of bf16 hardware.\n",
        );
    }
    s
}
