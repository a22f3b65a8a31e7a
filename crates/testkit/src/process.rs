//! One lock for the state a process has once: libtorch's default generator, its thread count, its
//! profiler and TF32 flag. A crate's integration tests are one test binary (`tests/it/main.rs`),
//! their tests threads of one process, so a test that seeds the generator and counts on the draws
//! that follow, or sets the thread count, must not run beside one that draws or computes meanwhile.
//!
//! [`ProcessLock::lock`] (a test that sets or seeds such state) runs alone among the tests that take
//! this lock; [`ProcessLock::shared`] (a test that only needs the state left as it is while it
//! compares two of its own computations) runs beside other such tests, not beside a `lock`. A
//! test that failed holding it does not fail the others: the lock is taken over, not poisoned.

use std::sync::{LockResult, PoisonError, RwLock, RwLockReadGuard, RwLockWriteGuard};

/// Held by a test that runs alone among those that take [`LIBTORCH`].
pub type Alone = RwLockWriteGuard<'static, ()>;
/// Held by a test that runs beside other readers, never beside an [`Alone`].
pub type Shared = RwLockReadGuard<'static, ()>;

/// A read-write lock whose exclusive side is spelt `lock()`, as the `Mutex<()>` each test file had
/// before its tests shared a process (`LIBTORCH.lock().unwrap_or_else(PoisonError::into_inner)`).
pub struct ProcessLock(RwLock<()>);

impl ProcessLock {
    /// The exclusive side, as `Mutex::lock` returns it (poisoned where a holder panicked).
    pub fn lock(&'static self) -> LockResult<Alone> {
        self.0.write()
    }

    /// The exclusive side, taken over from a test that failed holding it.
    pub fn alone(&'static self) -> Alone {
        self.0.write().unwrap_or_else(PoisonError::into_inner)
    }

    /// The shared side, taken over from a test that failed holding it.
    pub fn shared(&'static self) -> Shared {
        self.0.read().unwrap_or_else(PoisonError::into_inner)
    }
}

/// libtorch's process-wide state (generator, threads, profiler, matmul flags): one lock for a
/// test binary, whichever module its tests are in.
pub static LIBTORCH: ProcessLock = ProcessLock(RwLock::new(()));

/// [`LIBTORCH`], alone.
pub fn libtorch() -> Alone {
    LIBTORCH.alone()
}

/// [`LIBTORCH`], shared.
pub fn libtorch_shared() -> Shared {
    LIBTORCH.shared()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicBool, Ordering};

    #[test]
    fn readers_share_a_writer_is_alone_and_a_panic_does_not_poison() {
        static WRITING: AtomicBool = AtomicBool::new(false);
        let _ = std::thread::spawn(|| {
            let _g = libtorch();
            panic!("a failed test holding the lock");
        })
        .join();
        let (a, b) = (libtorch_shared(), libtorch_shared()); // two readers at once
        let writer = std::thread::spawn(|| {
            let _g = libtorch();
            WRITING.store(true, Ordering::SeqCst);
        });
        std::thread::sleep(std::time::Duration::from_millis(50));
        assert!(!WRITING.load(Ordering::SeqCst), "a writer ran beside readers");
        drop((a, b));
        writer.join().unwrap_or_else(|_| panic!("the writer failed"));
        assert!(WRITING.load(Ordering::SeqCst));
    }
}
