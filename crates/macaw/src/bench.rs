//! Meta-training speed (`promptdt bench --cases macaw_w<W>_t<T>`): one timed iteration is one
//! meta-step (zero the gradients; per task the inner steps of V and pi with second-order graphs and
//! the outer backward passes; the five Adams) of T tasks with batches of 256, cheetah dims 20/6,
//! width W. Its PyTorch twin is `scripts/bench/bench_macaw_torch.py` (the functional reference
//! `scripts/golden/macaw_torch.py`, same inputs).

use crate::{meta_step, Batch, Dims, Optimisers, Params};
use pdt_rundir::config::macaw::MacawConfig;
use std::time::Instant;
use tch::{Device, Kind, Tensor};

const OBS: usize = 20;
const ACT: usize = 6;
const BATCH: i64 = 256;

/// `macaw_w<W>_t<T>` -> (W, T).
pub fn parse_case(name: &str) -> Option<(usize, usize)> {
    let rest = name.strip_prefix("macaw_w")?;
    let (w, t) = rest.split_once("_t")?;
    let (w, t) = (w.parse().ok()?, t.parse().ok()?);
    (w > 0 && t > 0).then_some((w, t))
}

fn random_batch(device: Device) -> Batch {
    let o = (Kind::Float, device);
    Batch {
        obs: Tensor::randn([BATCH, OBS as i64], o) * 2.0,
        act: Tensor::rand([BATCH, ACT as i64], o) * 2.0 - 1.0,
        terminal_obs: Tensor::randn([BATCH, OBS as i64], o) * 2.0,
        terminal_discount: Tensor::rand([BATCH, 1], o),
        mc_return: Tensor::randn([BATCH, 1], o) * 30.0 + 50.0,
    }
}

/// Milliseconds per meta-step, `iters` of them after `warmup` untimed ones.
pub fn time_meta_steps(
    width: usize,
    tasks: usize,
    warmup: usize,
    iters: usize,
    device: Device,
) -> Vec<f64> {
    tch::manual_seed(0);
    let cfg = MacawConfig { width, ..MacawConfig::default() };
    let dims = Dims::new(OBS, ACT, width, cfg.depth);
    let mut p = Params::init(&dims, &cfg, Kind::Float, device);
    let mut opt = Optimisers::new(&p, &cfg);
    let batches: Vec<(Batch, Batch)> =
        (0..tasks).map(|_| (random_batch(device), random_batch(device))).collect();
    let sync = || {
        if let Device::Cuda(i) = device {
            tch::Cuda::synchronize(i as i64);
        }
    };
    let mut out = Vec::with_capacity(iters);
    for k in 0..warmup + iters {
        sync();
        let t0 = Instant::now();
        meta_step(&mut p, &mut opt, &dims, &batches, tasks, &cfg);
        sync();
        if k >= warmup {
            out.push(t0.elapsed().as_secs_f64() * 1e3);
        }
    }
    out
}
