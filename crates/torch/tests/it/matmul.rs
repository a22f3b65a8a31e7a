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
