//! Device selection: `cpu`, `cuda`, or `auto` (CUDA when present).
//!
//! A binary built on a machine without CUDA links only `libtorch_cpu`. On a GPU machine, pointing
//! `LD_LIBRARY_PATH` at a CUDA libtorch (same version, 2.11.0) and loading `libtorch_cuda.so` at run
//! time registers the CUDA backend with the already-loaded `libtorch_cpu`, so the same binary runs
//! on either.

// The request types are tch-free (`pdt_base::device`), so a run's configuration names them
// without libtorch; this module turns them into libtorch's settings.
use pdt_base::device::{DeviceSpec, Matmul};
use tch::Device;

#[derive(Debug, thiserror::Error)]
#[error("CUDA was asked for but is not available: {0}")]
pub struct DeviceError(String);

/// Loads `libtorch_cuda.so` (if it can be found on the library path) so that libtorch sees CUDA.
fn load_cuda_backend() -> Result<(), String> {
    // No `tch::Cuda::is_available()` before the dlopen: libtorch looks its CUDA hooks up once and
    // keeps the answer, so asking before `libtorch_cuda.so` is loaded pins "no CUDA" for the rest of
    // the process (seen on an H200: loaded, yet "no CUDA device"). dlopen of a loaded library is a
    // cheap reference count, so it is always done first.
    let name = c"libtorch_cuda.so";
    // SAFETY: dlopen with a valid NUL-terminated name; the handle is intentionally never closed, since
    // the library registers global state (the CUDA dispatch keys) that must outlive this call.
    #[allow(unsafe_code)]
    let handle = unsafe { libc::dlopen(name.as_ptr(), libc::RTLD_NOW | libc::RTLD_GLOBAL) };
    if handle.is_null() {
        return Err(
            "libtorch_cuda.so could not be loaded: install the CUDA part of libtorch 2.11.0 \
                    (python3 scripts/fetch_libtorch.py --cuda) and put the directory it prints on \
                    LD_LIBRARY_PATH"
                .into(),
        );
    }
    if tch::Cuda::is_available() {
        Ok(())
    } else {
        Err("libtorch_cuda.so loaded, but no CUDA device was found (is there a GPU, and an NVIDIA \
             driver for CUDA 13?)"
            .into())
    }
}

/// Resolves a device request.
pub fn resolve(spec: DeviceSpec) -> Result<Device, DeviceError> {
    match spec {
        DeviceSpec::Cpu => Ok(Device::Cpu),
        DeviceSpec::Cuda => load_cuda_backend().map(|()| Device::Cuda(0)).map_err(DeviceError),
        DeviceSpec::Auto => {
            Ok(if load_cuda_backend().is_ok() { Device::Cuda(0) } else { Device::Cpu })
        }
    }
}

/// A [`Matmul`] setting libtorch could not take.
#[derive(Debug, thiserror::Error)]
pub enum MatmulError {
    #[error(
        "matmul = tf32 needs a CUDA device, and the device is the CPU (the CPU computes \
         float32 products in fp32 only)"
    )]
    NeedsCuda,
    #[error(
        "matmul = bf16 needs hardware that computes bf16 natively, and {0}: use --matmul fp32 \
         (run.matmul = \"fp32\") instead, or set PROMPTDT_BF16_EMULATED=1 to emulate bf16 anyway \
         (slower than fp32; for tests and numerical comparisons)"
    )]
    NoNativeBf16(String),
    #[error("libtorch refused the matmul precision setting: {0}")]
    Refused(String),
}

/// Sets how the model's matrix products are computed for a run on `device` ([`Matmul`]). libtorch
/// keeps TF32 for the whole process, and [`crate::autocast::bf16`] is the process's too, so every
/// run of a process must ask for the same one (a pack checks that its runs agree). On a CUDA device
/// the TF32 switch is always set, so a `fp32` (or `bf16`) run is not TF32 even where the
/// environment asked libtorch for it (`TORCH_ALLOW_TF32_CUBLAS_OVERRIDE=1`, set in NVIDIA's
/// containers). On the CPU `tf32` is refused. `bf16` is refused where `device` has no native bf16
/// ([`crate::autocast::native`]) unless [`crate::autocast::EMULATED_ENV`] is `1`.
pub fn set_matmul(device: Device, matmul: Matmul) -> Result<(), MatmulError> {
    if matmul == Matmul::Bf16 {
        bf16_allowed(device)?;
    }
    if device.is_cuda() {
        set_cublas_tf32(matmul == Matmul::Tf32)?;
    } else if matmul == Matmul::Tf32 {
        return Err(MatmulError::NeedsCuda);
    }
    crate::autocast::set_bf16(matmul == Matmul::Bf16);
    Ok(())
}

/// Whether `bf16` may run on `device`: its hardware computes bf16 natively
/// ([`crate::autocast::native`]), or [`crate::autocast::EMULATED_ENV`] is `1`; and libtorch's
/// autocast opens there (once here, so that a forward pass's region, `autocast::scoped`, cannot
/// fail later). [`set_matmul`]'s check, without its process-wide effect.
pub fn bf16_allowed(device: Device) -> Result<(), MatmulError> {
    if !crate::autocast::emulation_allowed() {
        crate::autocast::native(device).map_err(MatmulError::NoNativeBf16)?;
    }
    drop(crate::autocast::Autocast::bf16(device).map_err(MatmulError::Refused)?);
    Ok(())
}

/// libtorch's cuBLAS TF32 switch itself (the process-wide flag; it only changes CUDA matmuls).
/// Public for measurements (`bench`'s TF32 check) and the test that checks it leaves CPU products
/// alone; runs go through [`set_matmul`].
#[doc(hidden)]
pub fn set_cublas_tf32(on: bool) -> Result<(), MatmulError> {
    // SAFETY: the C++ function catches every exception (none unwinds into Rust) and writes at most
    // `len` bytes, NUL included, into the buffer `call` gives it.
    #[allow(unsafe_code)]
    let set = |err, len| unsafe { crate::ffi::pdt_set_cublas_tf32(i32::from(on), err, len) };
    crate::ffi::call(set).map(|_| ()).map_err(MatmulError::Refused)
}

/// What libtorch will use for float32 matrix products on CUDA devices now (its cuBLAS TF32
/// switch; on the CPU products are fp32 whatever it says).
pub fn cuda_matmul() -> Result<Matmul, MatmulError> {
    // SAFETY: as in `set_cublas_tf32`.
    #[allow(unsafe_code)]
    let get = |err, len| unsafe { crate::ffi::pdt_cublas_tf32(err, len) };
    match crate::ffi::call(get).map_err(MatmulError::Refused)? {
        0 => Ok(Matmul::Fp32),
        _ => Ok(Matmul::Tf32),
    }
}

/// Host values as a tensor on `device`, without making the host wait: on CUDA through pinned
/// memory and an asynchronous copy. A plain `to_device` from pageable memory waits until the
/// stream has run everything queued before it, so each small upload in the middle of a step (a
/// mask, a pack's per-run factors) made the host's next kernel launches wait for the device's work
/// instead of overlapping it. (libtorch's pinned-memory cache keeps the host buffer until the copy
/// is done.) Elsewhere a plain copy.
pub fn upload<T: tch::kind::Element>(values: &[T], device: Device) -> tch::Tensor {
    let host = tch::Tensor::from_slice(values);
    if device.is_cuda() {
        // Should pinning fail (no pinned-memory allocator), the plain copy is still correct.
        match pinned(&host) {
            Ok(p) => p.to_device_(device, host.kind(), true, false),
            Err(_) => host.to_device(device),
        }
    } else {
        host.to_device(device)
    }
}

/// Patterns of flags (which runs of a pack are stepped, which have a prompt) uploaded once each
/// and reused: a pattern changes only when a run leaves, and on CUDA an upload costs about eight
/// host operators and a copy, every step otherwise.
#[derive(Debug, Default)]
pub struct BoolUploads {
    uploaded: std::collections::HashMap<Vec<bool>, tch::Tensor>,
}

impl BoolUploads {
    /// `flags` as a `[len]` bool tensor on `device` (the same device at every call).
    pub fn get(&mut self, flags: &[bool], device: Device) -> tch::Tensor {
        if let Some(t) = self.uploaded.get(flags) {
            return t.shallow_clone();
        }
        let t = upload(flags, device);
        self.uploaded.insert(flags.to_vec(), t.shallow_clone());
        t
    }
}

/// `host` copied into page-locked memory. Not tch's `pin_memory(device)`: libtorch 2.11 warns on
/// every call that passes a device (deprecated), two lines per upload of a CUDA run
/// (`csrc/memory.cpp`). Fails where libtorch has no pinned-memory allocator (no CUDA).
pub fn pinned(host: &tch::Tensor) -> Result<tch::Tensor, String> {
    let mut out: *mut std::ffi::c_void = std::ptr::null_mut();
    // SAFETY: `host.as_ptr()` is a live tch tensor handle (`at::Tensor*`) for the call; on success
    // the C++ side stores a new `at::Tensor*` allocated with `new`, as tch's own generated
    // functions return theirs, so `from_ptr` takes ownership of it (and frees it on drop).
    #[allow(unsafe_code)]
    let pin =
        |err, len| unsafe { crate::ffi::pdt_pin_memory(host.as_ptr().cast(), &mut out, err, len) };
    crate::ffi::call(pin)?;
    if out.is_null() {
        return Err("pin_memory returned no tensor".into());
    }
    // SAFETY: see above; `out` is non-null and owned by nobody else.
    #[allow(unsafe_code)]
    Ok(unsafe { tch::Tensor::from_ptr(out.cast()) })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pinned_copies_or_says_why() {
        let host = tch::Tensor::from_slice(&[1.0f32, 2.0, 3.0]);
        match resolve(DeviceSpec::Cuda) {
            // A GPU machine: the same values, page-locked on the host, and an upload through them.
            Ok(cuda) => {
                let p = pinned(&host).expect("pinned memory on a CUDA machine");
                assert_eq!(Vec::<f32>::try_from(&p).unwrap(), vec![1.0, 2.0, 3.0]);
                assert_eq!(p.device(), Device::Cpu);
                let up = upload(&[4i64, 5], cuda);
                assert_eq!(up.device(), cuda);
                assert_eq!(Vec::<i64>::try_from(&up.to_device(Device::Cpu)).unwrap(), vec![4, 5]);
            }
            // Without CUDA libtorch has no pinned allocator: libtorch's message, no panic.
            Err(_) => {
                let e = pinned(&host).expect_err("pinned memory without CUDA");
                assert!(e.contains("accelerator"), "{e}");
            }
        }
        // An upload to the CPU never pins.
        let up = upload(&[4i64, 5], Device::Cpu);
        assert_eq!(Vec::<i64>::try_from(&up).unwrap(), vec![4, 5]);
    }

    #[test]
    fn device_names_round_trip() {
        for spec in [DeviceSpec::Auto, DeviceSpec::Cpu, DeviceSpec::Cuda] {
            assert_eq!(spec.as_str().parse::<DeviceSpec>(), Ok(spec));
        }
        assert!("gpu".parse::<DeviceSpec>().unwrap_err().contains("gpu"));
    }

    #[test]
    fn upload_keeps_values_and_kind() {
        let t = upload(&[1.5f32, -2.0, 3.25], Device::Cpu);
        assert_eq!(t.kind(), tch::Kind::Float);
        assert_eq!(Vec::<f32>::try_from(&t).ok(), Some(vec![1.5, -2.0, 3.25]));
        let b = upload(&[true, false], Device::Cpu);
        assert_eq!(b.kind(), tch::Kind::Bool);
    }
}
