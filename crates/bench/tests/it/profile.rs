//! `bench --profile` on the CPU: libtorch's profiler counts what one iteration of a case runs.
//! What it shows about the batched pack: in the CUDA configuration (`_flat`: flat
//! optimiser, per-run mask draws, one LayerNorm for the pack) a step dispatches about as many
//! operators for 3 runs as for 1, which is what keeps a pack's GPU step near one run's number of
//! kernel launches; in the CPU configuration (`_pt`, a LayerNorm per run) each run adds hundreds.
//! The profiler is process-wide: it sees every thread's operators, so this crate's test binary
//! holds no other test that runs operators (or such a test and this one would take
//! `pdt_testkit::process::LIBTORCH`).
#![allow(clippy::unwrap_used)] // test: a failed unwrap is a failed test

use pdt_base::device::Matmul;
use pdt_bench::{run, BenchConfig};
use tch::Device;

#[test]
fn a_batched_pack_steps_with_about_one_runs_operators_in_the_cuda_configuration() {
    let cases = ["pack1_b2_flat", "pack3_b2_flat", "pack1_b2_pt", "pack3_b2_pt", "solo1_b2_flat"];
    let cfg = BenchConfig {
        threads: 1,
        iters: 1,
        warmup: 0,
        device: Device::Cpu,
        matmul: Matmul::Fp32,
        profile: true,
        cases: cases.map(String::from).to_vec(),
        pytorch: None,
        pytorch_eval_script: None,
        eval_episodes: 1,
        pytorch_rl_script: None,
        pytorch_macaw_script: None,
        serve_run: None,
        serve_steps: 2,
        serve_episodes: 1,
    };
    let report = run(&cfg).unwrap();
    let ops = |case: &str| report.profiles.iter().find(|p| p.case == case).unwrap().ops;
    for p in &report.profiles {
        assert!(p.ops > 1000.0, "{}: {} ops", p.case, p.ops);
        assert_eq!((p.kernels, p.copies), (0.0, 0.0), "{}: no CUDA on the CPU", p.case);
        assert!(!p.top.is_empty(), "{}", p.case);
    }
    let (flat, pt) =
        (ops("pack3_b2_flat") - ops("pack1_b2_flat"), ops("pack3_b2_pt") - ops("pack1_b2_pt"));
    // Measured (AMD EPYC, batch 2): 2 more runs add 19 operators with `_flat` (each run's mask
    // draw and its views: 2490 -> 2509; 12 runs 2536), 585 with `_pt` (4778 -> 5363).
    assert!(flat < 60.0, "two more runs added {flat} operators in the CUDA configuration");
    assert!(pt > 200.0, "two more runs added only {pt} operators with a LayerNorm per run");
    let md = pdt_bench::render_markdown(&report);
    assert!(md.contains("host ops per iteration") && md.contains("`pack3_b2_flat`:"), "{md}");
}
