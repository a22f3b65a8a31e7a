//! The kinds of benchmark case (which engine paths each runs, which has a PyTorch script), the
//! served cases, and the PyTorch baseline's report over the cases it has a script for.

use crate::{
    pack, parse_eval_case, render, run_pytorch, run_pytorch_eval, serve, BenchConfig, BenchError,
    EngineReport, PyTorchBaseline, ServeCase, EVAL_CASE,
};

/// A SAC / TD3 case (`pdt_rl::bench`), with its own PyTorch script.
pub(crate) fn is_rl(c: &str) -> bool {
    pdt_rl::bench::parse_case(c).is_some()
}

/// A MACAW meta-step case, with its own PyTorch script.
pub(crate) fn is_macaw(c: &str) -> bool {
    pdt_macaw::bench::parse_case(c).is_some()
}

pub(crate) fn is_eval(c: &str) -> bool {
    parse_eval_case(c).is_some()
}

/// `pack<N>_b<B>` / `solo<N>_b<B>`: promptdt only (`pack.rs`).
pub(crate) fn is_pack(c: &str) -> bool {
    pack::parse_case(c).is_some()
}

/// `serve_c<N>`: N concurrent clients of a served run.
pub(crate) fn serve_clients(c: &str) -> Option<usize> {
    c.strip_prefix("serve_c")?.parse().ok().filter(|&n: &usize| n > 0)
}

pub(crate) fn is_serve(c: &str) -> bool {
    serve_clients(c).is_some()
}

/// `render_<family>_<W>x<H>`: promptdt only (`render.rs`).
pub(crate) fn is_render(c: &str) -> bool {
    render::parse_case(c).is_some()
}

/// The `serve_c<N>` cases: a served run's latency and throughput under N clients.
pub(crate) fn serve_cases(cfg: &BenchConfig) -> Result<Vec<ServeCase>, BenchError> {
    let mut serve = Vec::new();
    for c in cfg.cases.iter().filter(|c| is_serve(c)) {
        let n = serve_clients(c).unwrap_or(1);
        let run = cfg.serve_run.as_ref().ok_or_else(|| BenchError::Baseline {
            cmd: c.clone(),
            why: "serve cases need --serve-run DIR (a trained run)".into(),
        })?;
        let t = serve::time_serve(run, n, cfg.serve_steps.max(2), cfg.serve_episodes.max(1))?;
        serve.push(ServeCase {
            name: c.clone(),
            clients: n,
            p50_ms: t.p50_ms,
            p99_ms: t.p99_ms,
            actions_per_s: t.actions_per_s,
            requests: t.requests,
        });
    }
    Ok(serve)
}

/// PyTorch on the cases it has a script for (`None` without a baseline or such cases): the
/// reference's paths only (training steps and full forwards), the evaluation loop, and the SAC /
/// TD3 and MACAW cases, each with its own script.
pub(crate) fn pytorch_report(cfg: &BenchConfig) -> Result<Option<EngineReport>, BenchError> {
    let train_cases: Vec<String> = cfg
        .cases
        .iter()
        .filter(|c| {
            !is_eval(c)
                && !is_rl(c)
                && !is_macaw(c)
                && !is_serve(c)
                && !is_pack(c)
                && !is_render(c)
                && !c.starts_with("act_b")
        })
        .cloned()
        .collect();
    let rl_cases: Vec<String> = cfg.cases.iter().filter(|c| is_rl(c)).cloned().collect();
    let macaw_cases: Vec<String> = cfg.cases.iter().filter(|c| is_macaw(c)).cloned().collect();
    let mut pytorch = match &cfg.pytorch {
        Some(b) if !train_cases.is_empty() => {
            Some(run_pytorch(b, &BenchConfig { cases: train_cases, ..cfg.clone() })?)
        }
        _ => None,
    };
    if let (Some(b), Some(script), true) =
        (&cfg.pytorch, &cfg.pytorch_eval_script, cfg.cases.iter().any(|c| c == EVAL_CASE))
    {
        let t = run_pytorch_eval(&b.python, script, cfg)?;
        let report = pytorch.get_or_insert_with(|| EngineReport {
            engine: "pytorch".into(),
            torch_version: None,
            threads: cfg.threads,
            results: vec![],
        });
        report.results.push(t);
    }
    for (script, cases) in
        [(&cfg.pytorch_rl_script, rl_cases), (&cfg.pytorch_macaw_script, macaw_cases)]
    {
        if let (Some(b), Some(script), false) = (&cfg.pytorch, script, cases.is_empty()) {
            let base = PyTorchBaseline { python: b.python.clone(), script: script.clone() };
            let t = run_pytorch(&base, &BenchConfig { cases, ..cfg.clone() })?;
            let report = pytorch.get_or_insert_with(|| EngineReport {
                engine: "pytorch".into(),
                torch_version: t.torch_version.clone(),
                threads: cfg.threads,
                results: vec![],
            });
            report.results.extend(t.results);
        }
    }
    Ok(pytorch)
}
