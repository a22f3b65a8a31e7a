//! How the process's C allocator treats the large blocks libtorch frees on the CPU.
//!
//! libtorch's CPU tensors come from `posix_memalign`, i.e. glibc's malloc. A training step at the
//! reference's large batch allocates and frees the same few hundred blocks every step, many of
//! them tens of megabytes (batch 560, 75 tokens: `[42000, 128]` activations are 21 MB, the MLP's
//! `[42000, 512]` 86 MB). glibc serves blocks above its mmap threshold (dynamic, at most 32 MB)
//! with a fresh `mmap` and gives them back with `munmap` on free, and it trims the top of the heap
//! when more than its trim threshold is free there: either way the next step touches new pages and
//! the kernel zero-fills every one of them on first touch. Measured with `perf` on `promptdt bench
//! --cases train_b560 --threads 1` (AVX2 EPYC): 2.28 M page faults over four steps, a fifth of
//! the samples in the kernel's fault path and page zeroing (PyTorch's own process has the same
//! churn, a little less by luck of its heap layout: 1.45 M). With this setting (and one op less
//! in the attention's backward) a step's CPU time went from 4.4 s to 2.8 s (PyTorch: 3.2 s).
//!
//! [`keep_freed_memory`] makes glibc serve every block from the heap and never trim it, so the
//! memory of one step is reused by the next: once the heap has grown to a step's peak (two steps),
//! a step takes no page faults.
//! The resident size stays at the peak of a step (which it reaches every step anyway). It covers
//! the main thread's allocations (glibc's main arena), where `promptdt` trains and evaluates; a
//! block above 64 MB asked for on another thread is still served by its own mmap (glibc's
//! per-thread arenas fall back to mmap whatever `M_MMAP_MAX` says). Nothing
//! else changes: the same kernels run on the same values, so results are bit-identical (the
//! parity tests do not call this and still pass; a training run gives byte-identical checkpoints
//! with it and without it).

/// What [`keep_freed_memory`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HostMemory {
    /// glibc now serves every block from the heap and never returns freed memory to the kernel.
    Kept,
    /// glibc refused one of the settings (the allocator stays as it was, or half-set).
    Refused,
    /// Not glibc (another libc, another OS): nothing was changed.
    Unsupported,
}

/// Tells glibc's malloc to keep freed memory for reuse instead of unmapping or trimming it (see the
/// module docs). Call it once, early in a process that trains or evaluates (the `promptdt` binary
/// does, before parsing its arguments); it is process-wide and cheap, and calling it again is
/// harmless. The environment can still override it (`MALLOC_MMAP_MAX_`, `MALLOC_TRIM_THRESHOLD_`
/// are read by glibc before `main`, and this call overrides them in turn).
pub fn keep_freed_memory() -> HostMemory {
    imp::keep_freed_memory()
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
mod imp {
    use super::HostMemory;

    pub fn keep_freed_memory() -> HostMemory {
        // M_MMAP_MAX = 0: no block is served by its own mmap (which munmap would give back on free);
        // M_TRIM_THRESHOLD = -1: never trim the top of the heap (mallopt(3) documents -1 as "disables
        // trimming completely").
        // SAFETY: mallopt only changes glibc's allocator parameters (under its own lock); it takes
        // plain integers and touches no memory of ours.
        #[allow(unsafe_code)]
        let ok = unsafe {
            libc::mallopt(libc::M_MMAP_MAX, 0) == 1
                && libc::mallopt(libc::M_TRIM_THRESHOLD, -1) == 1
        };
        if ok {
            HostMemory::Kept
        } else {
            HostMemory::Refused
        }
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
mod imp {
    use super::HostMemory;

    pub fn keep_freed_memory() -> HostMemory {
        HostMemory::Unsupported
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glibc_accepts_the_settings() {
        let expected = if cfg!(all(target_os = "linux", target_env = "gnu")) {
            HostMemory::Kept
        } else {
            HostMemory::Unsupported
        };
        assert_eq!(keep_freed_memory(), expected);
        // Idempotent: a second call is accepted as well.
        assert_eq!(keep_freed_memory(), expected);
    }
}
