//! `pdt_envs::bench` with a tiny budget: the result rows, their counts and rates.
//!
//! The full-size run (the numbers of `benchmarks/05-envs.json`) is the ignored test `full_size`:
//! `CARGO_TARGET_DIR=/work/target-mujoco cargo test --release -p pdt-envs --test it \
//!  bench_smoke::full_size -- --ignored --nocapture`
//! (environment variables `PDT_BENCH_STEPS`, `PDT_BENCH_ENVS`, `PDT_BENCH_THREADS` (e.g. `1,2`),
//! `PDT_BENCH_FAMILIES` (e.g. `cheetah_vel,ant_dir`) and `PDT_BENCH_SEED` override the defaults).
//! It prints one JSON line per result and one with the machine's load.

use pdt_envs::bench::{self, BenchMode, EnvBenchConfig, EnvBenchResult};
use pdt_envs::EnvError;

fn ok<T>(r: Result<T, EnvError>) -> T {
    r.unwrap_or_else(|e| panic!("{e}"))
}

fn tiny(families: &[&str], steps: usize) -> EnvBenchConfig {
    EnvBenchConfig {
        families: families.iter().map(|s| s.to_string()).collect(),
        steps_per_env: steps,
        vec_envs: 4,
        threads: vec![1, 2, 3],
        seed: 7,
    }
}

fn check_rate(r: &EnvBenchResult) {
    assert!(r.seconds > 0.0 && r.seconds.is_finite(), "{r:?}");
    assert!(r.steps_per_s > 0.0 && r.steps_per_s.is_finite(), "{r:?}");
    let want = r.steps as f64 / r.seconds;
    assert!((r.steps_per_s - want).abs() <= 1e-9 * want, "{r:?}");
}

#[test]
fn rows_counts_and_rates_are_sane() {
    // 250 steps: every episode ends at the latest at step 200 (the horizon), so each environment
    // resets at least once; HalfCheetah never terminates, so it resets exactly once.
    let cfg = tiny(&["cheetah_vel", "ant_dir"], 250);
    let results = ok(bench::run(&cfg));
    assert_eq!(results.len(), 2 * (1 + 3));
    for (f, family) in ["cheetah_vel", "ant_dir"].into_iter().enumerate() {
        let rows = &results[f * 4..(f + 1) * 4];
        let single = &rows[0];
        assert_eq!(single.family, family);
        assert_eq!(single.mode, BenchMode::Single);
        assert_eq!((single.threads, single.envs, single.steps), (1, 1, 250));
        check_rate(single);
        for (r, threads) in rows[1..].iter().zip([1, 2, 3]) {
            assert_eq!(r.family, family);
            assert_eq!(r.mode, BenchMode::Vec);
            assert_eq!((r.threads, r.envs, r.steps), (threads, 4, 4 * 250));
            check_rate(r);
        }
        if family == "cheetah_vel" {
            assert_eq!(single.resets, 1);
            assert!(rows[1..].iter().all(|r| r.resets == 4), "{rows:?}");
        } else {
            assert!(single.resets >= 1, "{single:?}");
            assert!(rows[1..].iter().all(|r| r.resets >= 4), "{rows:?}");
        }
        // Same seeds and actions for every thread count: the same episodes, so the same resets.
        assert!(rows[2..].iter().all(|r| r.resets == rows[1].resets), "{rows:?}");
    }
}

#[test]
fn threads_beyond_the_env_count_are_capped_and_modes_serialize() {
    let cfg = EnvBenchConfig {
        families: vec!["cheetah_dir".into()],
        steps_per_env: 20,
        vec_envs: 2,
        threads: vec![0, 8],
        seed: 1,
    };
    let results = ok(bench::run(&cfg));
    assert_eq!(results.len(), 3);
    assert_eq!((results[1].threads, results[2].threads), (1, 2));
    assert!(results.iter().all(|r| r.resets == 0));
    let json = serde_json::to_value(&results).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(json[0]["mode"], "single");
    assert_eq!(json[1]["mode"], "vec");
    assert_eq!(json[2]["steps"], 40);
}

#[test]
fn contact_cost_variant_and_no_vec_runs() {
    let cfg = EnvBenchConfig {
        families: vec![bench::ANT_DIR_CONTACT.into()],
        steps_per_env: 30,
        vec_envs: 0,
        threads: vec![],
        seed: 3,
    };
    let results = ok(bench::run(&cfg));
    assert_eq!(results.len(), 1);
    assert_eq!((results[0].family.as_str(), results[0].steps), (bench::ANT_DIR_CONTACT, 30));
    check_rate(&results[0]);
}

#[test]
fn bad_configs_are_refused() {
    let mut cfg = tiny(&["cheetah_vel", "hopper_vel"], 10);
    assert!(matches!(bench::run(&cfg), Err(EnvError::UnknownEnv(..))));
    cfg.families = vec!["cheetah_vel".into()];
    cfg.steps_per_env = 0;
    assert!(bench::run(&cfg).is_err());
    cfg.steps_per_env = 10;
    cfg.vec_envs = 0;
    assert!(bench::run(&cfg).is_err());
}

fn env_var<T: std::str::FromStr>(name: &str) -> Option<T> {
    std::env::var(name).ok().and_then(|v| v.trim().parse().ok())
}

fn env_list(name: &str) -> Option<Vec<String>> {
    let v = std::env::var(name).ok()?;
    Some(v.split(',').map(|s| s.trim().to_string()).filter(|s| !s.is_empty()).collect())
}

/// The full-size numbers; run with `--release -- --ignored --nocapture full_size`.
#[test]
#[ignore = "full-size benchmark: minutes in release mode"]
fn full_size() {
    let mut cfg = EnvBenchConfig::default();
    if let Some(v) = env_var("PDT_BENCH_STEPS") {
        cfg.steps_per_env = v;
    }
    if let Some(v) = env_var("PDT_BENCH_ENVS") {
        cfg.vec_envs = v;
    }
    if let Some(v) = env_var("PDT_BENCH_SEED") {
        cfg.seed = v;
    }
    if let Some(v) = env_list("PDT_BENCH_THREADS") {
        cfg.threads = v.iter().map(|s| s.parse().unwrap_or_else(|e| panic!("{s}: {e}"))).collect();
    }
    if let Some(v) = env_list("PDT_BENCH_FAMILIES") {
        cfg.families = v;
    }
    let load_before = bench::load_avg_1m();
    let results = ok(bench::run(&cfg));
    for r in &results {
        println!("{}", serde_json::to_string(r).unwrap_or_else(|e| panic!("{e}")));
    }
    println!(
        "{}",
        serde_json::json!({
            "engine": "pdt-envs",
            "config": cfg,
            "cores": pdt_base::threads::available_cores(),
            "load_avg_1m_before": load_before,
            "load_avg_1m_after": bench::load_avg_1m(),
        })
    );
}
