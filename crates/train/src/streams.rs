//! The lock on libtorch's global generator. The run seed's streams themselves are numbered in
//! `pdt_run::streams`, beside the evaluation plans that draw from them.

/// libtorch's random generator (weight init, dropout) is global to the process: runs in one process
/// take turns, so that each run's draws depend on its seed alone.
static TORCH_RNG: std::sync::Mutex<()> = std::sync::Mutex::new(());

pub fn torch_rng_lock() -> std::sync::MutexGuard<'static, ()> {
    TORCH_RNG.lock().unwrap_or_else(|e| e.into_inner())
}
