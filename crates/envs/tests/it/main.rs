//! The integration tests of `pdt-envs`, one test binary: each `NAME.rs` here is a module (a test
//! file of its own before), run alone with `cargo test -p pdt-envs --test it NAME::`. One binary a
//! crate, not one a file: linking test binaries (libtorch, MuJoCo) was most of the build. The
//! modules' tests are threads of one process: a test that seeds libtorch's generator or sets its
//! process-wide state takes `pdt_testkit::process::LIBTORCH`.
//!
//! Kept a test binary of its own, where a fresh process is the point: `tests/mujoco_logging.rs`
//! (the logger must be in place before the process loads its first model).

mod support;

mod ant_symmetry;
mod bench_smoke;
mod collect_policy;
mod dial_collect;
mod dial_parity;
mod metaworld_collect;
mod metaworld_parity;
mod mujoco_envs;
mod point_robot;
mod render;
mod replay_fuzz;
mod replay_parity;
mod reward_check;
mod suite;
mod vec_env;
mod vec_env_backend;
mod worker;
