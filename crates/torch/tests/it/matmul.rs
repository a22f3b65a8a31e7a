//! The `run.matmul` switch reaches libtorch (csrc/matmul.cpp) and changes CUDA matmuls only: on the
//! CPU, products stay bit-identical whichever way libtorch's TF32 flag is set. (Its effect on a GPU
//! is measured by `promptdt bench --device cuda --matmul tf32`.) The flag is process-wide: the
//! test holds the test binary's libtorch lock (`pdt_testkit::process`), so no other test computes
//! meanwhile.
#![allow(clippy::unwrap_used)] // test: a failed unwrap is a failed test

use pdt_base::device::Matmul;
use pdt_torch::device::{cuda_matmul, set_cublas_tf32, set_matmul, MatmulError};
use tch::{Device, Kind, Tensor};

/// CPU products of the shapes a training step computes (a linear layer, attention's batched
/// products), as bits.
fn cpu_products() -> Vec<u32> {
    tch::manual_seed(7);
    let x = Tensor::randn([64, 75, 128], (Kind::Float, Device::Cpu));
    let w = Tensor::randn([512, 128], (Kind::Float, Device::Cpu));
    let lin = x.linear(&w, None::<Tensor>);
    let att = x.matmul(&x.transpose(1, 2));
    let mm = x.reshape([-1, 128]).mm(&w.tr());
    let mut bits = Vec::new();
    for t in [lin, att, mm] {
        let v: Vec<f32> = t.flatten(0, -1).try_into().unwrap();
        bits.extend(v.iter().map(|f| f.to_bits()));
    }
    bits
}

#[test]
fn tf32_switch_reaches_libtorch_and_leaves_cpu_products_alone() {
    let _g = pdt_testkit::process::libtorch();
    let overridden = std::env::var("TORCH_ALLOW_TF32_CUBLAS_OVERRIDE").is_ok_and(|v| v == "1");
    if !overridden {
        assert_eq!(cuda_matmul().unwrap(), Matmul::Fp32, "libtorch's default is fp32");
    }
    // A run on the CPU: fp32 is a no-op, tf32 is refused by name.
    set_matmul(Device::Cpu, Matmul::Fp32).unwrap();
    let e = set_matmul(Device::Cpu, Matmul::Tf32).unwrap_err();
    assert!(matches!(e, MatmulError::NeedsCuda), "{e}");
    assert!(e.to_string().contains("tf32 needs a CUDA device"), "{e}");

    let before = cpu_products();
    set_cublas_tf32(true).unwrap();
    assert_eq!(cuda_matmul().unwrap(), Matmul::Tf32, "the switch reached libtorch");
    let during = cpu_products();
    set_cublas_tf32(false).unwrap();
    assert_eq!(cuda_matmul().unwrap(), Matmul::Fp32);
    assert_eq!(before.len(), during.len());
    let differing = before.iter().zip(&during).filter(|(a, b)| a != b).count();
    assert_eq!(differing, 0, "CPU products changed with cuBLAS's TF32 flag on");
}

/// `bf16` where the CPU has no native bf16 is refused by name, with the flag to use instead and the
/// escape hatch; the escape hatch lets it through; `fp32` afterwards turns it off. Where the CPU
/// has native bf16, it is accepted without the escape hatch.
#[test]
fn bf16_refused_without_native_bf16_unless_emulation_is_asked_for() {
    use pdt_torch::autocast::{bf16, native_cpu, EMULATED_ENV};
    let _g = pdt_testkit::process::libtorch();
    let before = std::env::var_os(EMULATED_ENV);
    // The variable is the process's: set and restored under the libtorch lock.
    std::env::remove_var(EMULATED_ENV);
    match native_cpu() {
        Ok(()) => {
            set_matmul(Device::Cpu, Matmul::Bf16).unwrap();
            assert!(bf16(), "native bf16: accepted without the escape hatch");
        }
        Err(why) => {
            let e = set_matmul(Device::Cpu, Matmul::Bf16).unwrap_err();
            assert!(matches!(e, MatmulError::NoNativeBf16(_)), "{e}");
            let msg = e.to_string();
            for part in ["bf16", "--matmul fp32", "PROMPTDT_BF16_EMULATED=1", why.as_str()] {
                assert!(msg.contains(part), "the refusal names `{part}`: {msg}");
            }
            assert!(!bf16(), "a refused bf16 leaves the process in fp32");
        }
    }
    std::env::set_var(EMULATED_ENV, "1");
    let emulated = set_matmul(Device::Cpu, Matmul::Bf16);
    let on = bf16();
    set_matmul(Device::Cpu, Matmul::Fp32).unwrap();
    let off = !bf16();
    match before {
        Some(v) => std::env::set_var(EMULATED_ENV, v),
        None => std::env::remove_var(EMULATED_ENV),
    }
    emulated.unwrap();
    assert!(on, "emulation asked for: bf16 on");
    assert!(off, "fp32 turns bf16 off");
}
