//! bf16 mixed precision (`run.matmul = "bf16"`, `pdt_base::device::Matmul::Bf16`): libtorch's own
//! autocast, entered around each forward pass as `torch.autocast(device_type, dtype=torch.bfloat16)`
//! is (`csrc/autocast.cpp`), and whether the hardware computes bf16 natively.
//!
//! Inside the region libtorch casts per op, from its own lists: matrix products (`addmm`, `linear`,
//! `matmul`, `bmm`, ...) take bfloat16 inputs and accumulate in float32; ops on its float32 list run
//! in float32; the rest run in their inputs' type. So it is PyTorch's autocast, not a copy of it.
//! The weights (the optimiser's master copy) stay float32 and are cast once per forward pass (the
//! autocast cache); the backward pass runs outside the region, as PyTorch recommends, in the types
//! the forward recorded. Where promptdt differs is said where it does (`pdt_model::PromptDt`).
//!
//! The setting is the process's (as cuBLAS's TF32 switch is): [`crate::device::set_matmul`] turns it
//! on or off, a model built afterwards takes it (`pdt_model::PromptDt::new`), and each of its
//! forward passes opens a region ([`scoped`]). libtorch's autocast state itself is per thread,
//! which is why it is entered around each pass, on the thread that runs it.

use std::ffi::c_int;
use std::sync::atomic::{AtomicBool, Ordering};
use tch::Device;

/// The environment variable that lets `bf16` run where the hardware has no native bf16: libtorch
/// then converts to and from bf16 around float32 arithmetic (the same rounding, so the same
/// results as native hardware up to summation order, but slower than fp32). For tests and for
/// comparing numerics on any machine; never for timing.
pub const EMULATED_ENV: &str = "PROMPTDT_BF16_EMULATED";

static BF16: AtomicBool = AtomicBool::new(false);

/// Whether forward passes of this process run under bf16 autocast (`run.matmul = "bf16"`).
pub fn bf16() -> bool {
    BF16.load(Ordering::SeqCst)
}

/// Sets [`bf16`] (through [`crate::device::set_matmul`], which checks the hardware first).
pub(crate) fn set_bf16(on: bool) {
    BF16.store(on, Ordering::SeqCst);
}

/// Whether [`EMULATED_ENV`] is `1`.
pub fn emulation_allowed() -> bool {
    std::env::var(EMULATED_ENV).is_ok_and(|v| v.trim() == "1")
}

/// An open bf16 autocast region on this thread; dropping it closes the region (restoring what was
/// there before, as `torch.autocast.__exit__` does).
#[derive(Debug)]
pub struct Autocast {
    cuda: c_int,
    prev: [c_int; 3],
    // libtorch's autocast state is thread-local: the region must close on the thread it opened on.
    _not_send: std::marker::PhantomData<*const ()>,
}

impl Autocast {
    /// Opens a bf16 autocast region for `device`'s type (CPU or CUDA) on this thread.
    pub fn bf16(device: Device) -> Result<Self, String> {
        let cuda = c_int::from(device.is_cuda());
        let mut prev = [0 as c_int; 3];
        // SAFETY: `prev` holds the 3 ints the C++ function writes; it catches every exception.
        #[allow(unsafe_code)]
        let enter =
            |err, len| unsafe { crate::ffi::pdt_autocast_enter(cuda, prev.as_mut_ptr(), err, len) };
        crate::ffi::call(enter)?;
        Ok(Self { cuda, prev, _not_send: std::marker::PhantomData })
    }
}

impl Drop for Autocast {
    fn drop(&mut self) {
        let (cuda, prev) = (self.cuda, self.prev);
        // SAFETY: as in `Autocast::bf16`; `prev` is what enter wrote.
        #[allow(unsafe_code)]
        let exit =
            |err, len| unsafe { crate::ffi::pdt_autocast_exit(cuda, prev.as_ptr(), err, len) };
        // Restoring the flags cannot fail for the CPU or CUDA (the only device types opened);
        // a drop has no caller to tell anyway.
        let _ = crate::ffi::call(exit);
    }
}

/// Whether a bf16 (or any) autocast region is open for `device`'s type on this thread.
pub fn active(device: Device) -> Result<bool, String> {
    let cuda = c_int::from(device.is_cuda());
    // SAFETY: the C++ function catches every exception.
    #[allow(unsafe_code)]
    let get = |err, len| unsafe { crate::ffi::pdt_autocast_enabled(cuda, err, len) };
    crate::ffi::call(get).map(|on| on != 0)
}

/// `f()` inside a bf16 autocast region for `device` when `on` (a model built while the process
/// computes in bf16, [`bf16`]), plainly otherwise (fp32 and tf32 run exactly the ops they ran
/// before).
pub fn scoped<T>(on: bool, device: Device, f: impl FnOnce() -> T) -> T {
    if !on {
        return f();
    }
    // `set_matmul` opened and closed a region before turning bf16 on, so this cannot fail where it
    // did not: libtorch throws only for device types without autocast.
    #[allow(clippy::expect_used)]
    let _region = Autocast::bf16(device).expect("libtorch's autocast opened once already");
    f()
}

/// Ok if `device` computes bf16 natively; else why not, in words (naming what is missing).
pub fn native(device: Device) -> Result<(), String> {
    if device.is_cuda() {
        let (major, minor) = cuda_capability()?;
        if major >= 8 {
            return Ok(());
        }
        return Err(format!(
            "the GPU (compute capability {major}.{minor}) has no bf16 tensor cores (8.0 and later do)"
        ));
    }
    native_cpu()
}

/// The CPU's model name and flags (`/proc/cpuinfo`'s first processor), for [`native_cpu`].
fn cpu_info() -> Option<(String, Vec<String>)> {
    let text = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    let mut model = String::new();
    let mut flags = Vec::new();
    for line in text.lines() {
        let Some((k, v)) = line.split_once(':') else { continue };
        match k.trim() {
            // x86: "model name"; ARM: "CPU part" is a number, so the model stays empty there.
            "model name" if model.is_empty() => model = v.trim().to_string(),
            // x86 "flags", ARM "Features": the first processor's.
            "flags" | "Features" if flags.is_empty() => {
                flags = v.split_whitespace().map(str::to_string).collect();
            }
            _ => {}
        }
    }
    Some((model, flags))
}

/// The CPU flags that mean native bf16 arithmetic: Intel AMX-BF16 (Sapphire Rapids and later),
/// AVX512-BF16 (Intel Cooper Lake and later, AMD Zen 4 and later), ARMv8.6 BF16. libtorch (oneDNN)
/// runs bf16 products on these; without them it converts around float32 kernels.
pub const NATIVE_CPU_FLAGS: [&str; 3] = ["amx_bf16", "avx512_bf16", "bf16"];

/// [`native`] for the CPU: read from the flags the kernel reports (`/proc/cpuinfo`), as libtorch's
/// own dispatch reads the CPU's features.
pub fn native_cpu() -> Result<(), String> {
    let Some((model, flags)) = cpu_info() else {
        return Err("the CPU's features could not be read (/proc/cpuinfo)".into());
    };
    if flags.iter().any(|f| NATIVE_CPU_FLAGS.contains(&f.as_str())) {
        return Ok(());
    }
    let name = if model.is_empty() { "the CPU".to_string() } else { format!("the CPU ({model})") };
    Err(format!("{name} reports none of AMX-BF16, AVX512-BF16 or ARM BF16 (/proc/cpuinfo flags)"))
}

/// Device 0's compute capability, from the CUDA runtime libtorch's CUDA part loaded
/// (`cudaDeviceGetAttribute`; tch binds no device properties).
fn cuda_capability() -> Result<(c_int, c_int), String> {
    type GetAttribute = unsafe extern "C" fn(*mut c_int, c_int, c_int) -> c_int;
    // cudaDevAttrComputeCapabilityMajor / Minor.
    const MAJOR: c_int = 75;
    const MINOR: c_int = 76;
    let name = c"cudaDeviceGetAttribute";
    // SAFETY: dlsym/dlopen with valid NUL-terminated names. The runtime was loaded with
    // libtorch_cuda.so (RTLD_GLOBAL, `device::resolve`); RTLD_NOLOAD only finds a loaded one.
    #[allow(unsafe_code)]
    let sym = unsafe {
        let mut s = libc::dlsym(libc::RTLD_DEFAULT, name.as_ptr());
        if s.is_null() {
            for lib in [c"libcudart.so.13", c"libcudart.so.12", c"libcudart.so"] {
                let h = libc::dlopen(lib.as_ptr(), libc::RTLD_NOW | libc::RTLD_NOLOAD);
                if !h.is_null() {
                    s = libc::dlsym(h, name.as_ptr());
                    if !s.is_null() {
                        break;
                    }
                }
            }
        }
        s
    };
    if sym.is_null() {
        return Err(
            "the GPU's compute capability could not be read (no CUDA runtime loaded)".into()
        );
    }
    // SAFETY: the symbol is the CUDA runtime's `cudaError_t cudaDeviceGetAttribute(int*,
    // cudaDeviceAttr, int)` (an int-sized enum), called with valid pointers.
    #[allow(unsafe_code)]
    let (rc, major, minor) = unsafe {
        let get: GetAttribute = std::mem::transmute::<*mut libc::c_void, GetAttribute>(sym);
        let (mut major, mut minor) = (0, 0);
        let rc = get(&mut major, MAJOR, 0) | get(&mut minor, MINOR, 0);
        (rc, major, minor)
    };
    if rc != 0 {
        return Err(format!("the GPU's compute capability could not be read (CUDA error {rc})"));
    }
    Ok((major, minor))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_region_opens_closes_and_nests() {
        let cpu = Device::Cpu;
        assert_eq!(active(cpu), Ok(false));
        {
            let _outer = Autocast::bf16(cpu).expect("autocast on the CPU");
            assert_eq!(active(cpu), Ok(true));
            {
                let _inner = Autocast::bf16(cpu).expect("nested");
                let x = tch::Tensor::ones([2, 3], (tch::Kind::Float, cpu));
                let y = tch::Tensor::ones([3, 2], (tch::Kind::Float, cpu));
                assert_eq!(x.matmul(&y).kind(), tch::Kind::BFloat16, "products in bf16");
                // Outside autocast's lists: the input's type.
                assert_eq!(x.softmax(-1, None::<tch::Kind>).kind(), tch::Kind::Float);
            }
            assert_eq!(active(cpu), Ok(true), "the inner region restores the outer one");
        }
        assert_eq!(active(cpu), Ok(false));
        let x = tch::Tensor::ones([2, 2], (tch::Kind::Float, cpu));
        assert_eq!(x.matmul(&x).kind(), tch::Kind::Float, "fp32 again after the region");
    }

    #[test]
    fn native_says_why_not() {
        // Whatever this CPU is, the answer names what it looked for when it says no.
        if let Err(why) = native_cpu() {
            assert!(why.contains("AVX512-BF16") || why.contains("/proc/cpuinfo"), "{why}");
        }
    }
}
