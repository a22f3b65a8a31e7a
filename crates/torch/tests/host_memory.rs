//! `pdt_torch::host_memory::keep_freed_memory` does what it is for: a training step at a large
//! batch reuses the memory the previous step freed instead of faulting in fresh zeroed pages.
//!
//! A test without libtest's harness (`harness = false` in Cargo.toml): the setting covers the
//! main thread's allocations (glibc's main arena), and libtest runs every test on a thread of its
//! own, whose arena serves large blocks with mmap whatever the setting says.
#![allow(clippy::unwrap_used)] // a test: a failed unwrap is a failed test

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn main() {
    use pdt_torch::host_memory::{keep_freed_memory, HostMemory};
    use tch::{Device, Kind, Tensor};

    /// Minor page faults of the whole process so far (libtorch's worker threads touch pages too).
    fn minor_faults() -> i64 {
        // SAFETY: getrusage writes one `rusage` into the zeroed struct we pass and reads nothing.
        #[allow(unsafe_code)]
        let usage = unsafe {
            let mut usage: libc::rusage = std::mem::zeroed();
            assert_eq!(libc::getrusage(libc::RUSAGE_SELF, &mut usage), 0);
            usage
        };
        usage.ru_minflt
    }

    tch::manual_seed(0);
    let opts = (Kind::Float, Device::Cpu);
    // The shape of a Prompt-DT training step's blocks at batch 320 (75 tokens, hidden 128, MLP
    // 512): 24000 rows, whose MLP activations `[24000, 512]` f32 are 49 MB, above glibc's largest
    // mmap threshold (32 MB), as at the reference's batch 560. Three MLP layers, forward and
    // backward: the step allocates and frees a few dozen such blocks (the model itself is
    // `pdt-model`'s; this crate is below it, and the allocator sees only block sizes).
    let rows = 24_000;
    let x = Tensor::randn([rows, 128], opts);
    let layers: Vec<(Tensor, Tensor)> = (0..3)
        .map(|_| {
            let up = (Tensor::randn([128, 512], opts) * 0.05).set_requires_grad(true);
            let down = (Tensor::randn([512, 128], opts) * 0.05).set_requires_grad(true);
            (up, down)
        })
        .collect();
    let step_faults = || {
        let before = minor_faults();
        let mut h = x.shallow_clone();
        for (up, down) in &layers {
            h = &h + h.mm(up).relu().mm(down);
        }
        h.square().mean(Kind::Float).backward();
        for (up, down) in &layers {
            let _ = up.grad().zero_();
            let _ = down.grad().zero_();
        }
        minor_faults() - before
    };
    // Steady state by default: every step faults in its large blocks again.
    step_faults();
    let by_default = step_faults();
    assert_eq!(keep_freed_memory(), HostMemory::Kept);
    // The heap grows to the step's peak over the first steps (measured: two), then stays.
    step_faults();
    step_faults();
    let kept = step_faults();
    println!("page faults of a training-sized step: {by_default} by default, {kept} kept");
    // The test can fail: by default a step faults in at least its MLP activations (12000 pages
    // each, several per layer).
    assert!(by_default > 50_000, "by default a step took only {by_default} page faults");
    assert!(kept * 20 < by_default, "{kept} page faults per step with the memory kept");
    println!("host_memory: ok");
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn main() {}
