//! Where a meta-step's time goes (tasks vs the Adams), to tell whether the tasks' second-order
//! graphs or the optimisers bound a meta-step.
//! `cargo run --release -p pdt-macaw --example profile_step -- [width] [tasks] [threads]`
use pdt_macaw::*;
use pdt_rundir::config::macaw::MacawConfig;
use std::time::Instant;
use tch::{Device, Kind, Tensor};

fn main() {
    let args: Vec<usize> = std::env::args().skip(1).filter_map(|a| a.parse().ok()).collect();
    let (w, t, th) = (
        args.first().copied().unwrap_or(100),
        args.get(1).copied().unwrap_or(2),
        args.get(2).copied().unwrap_or(1),
    );
    tch::set_num_threads(th as i32);
    tch::manual_seed(0);
    let cfg = MacawConfig { width: w, ..Default::default() };
    let dims = Dims::new(20, 6, w, 3);
    let mut p = Params::init(&dims, &cfg, Kind::Float, Device::Cpu);
    let mut opt = Optimisers::new(&p, &cfg);
    let o = (Kind::Float, Device::Cpu);
    let batch = || Batch {
        obs: Tensor::randn([256, 20], o),
        act: Tensor::rand([256, 6], o),
        terminal_obs: Tensor::randn([256, 20], o),
        terminal_discount: Tensor::rand([256, 1], o),
        mc_return: Tensor::randn([256, 1], o) * 30.0,
    };
    let tasks: Vec<(Batch, Batch)> = (0..t).map(|_| (batch(), batch())).collect();
    let (mut a, mut b) = (0.0, 0.0);
    for k in 0..12 {
        p.zero_grad();
        let t0 = Instant::now();
        for (i, o) in &tasks {
            meta_task(&p, &dims, i, o, t, &cfg);
        }
        let t1 = Instant::now();
        opt.step(&p);
        let t2 = Instant::now();
        if k >= 2 {
            a += (t1 - t0).as_secs_f64() * 100.0;
            b += (t2 - t1).as_secs_f64() * 100.0;
        }
    }
    println!("width {w} tasks {t} threads {th}: tasks {a:.1} ms, adam {b:.1} ms per meta-step");
}
