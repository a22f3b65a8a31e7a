//! A device request as a configuration names it: `cpu`, `cuda`, or `auto` (CUDA when present).
//! Resolving it to a libtorch device is `pdt_torch::device::resolve`; the request itself carries no
//! libtorch, so a run's configuration can be read without it.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DeviceSpec {
    #[default]
    Auto,
    Cpu,
    Cuda,
}

impl std::str::FromStr for DeviceSpec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Self::Auto),
            "cpu" => Ok(Self::Cpu),
            "cuda" => Ok(Self::Cuda),
            other => Err(format!("unknown device `{other}` (expected cpu, cuda or auto)")),
        }
    }
}

impl DeviceSpec {
    /// The name `from_str` takes back (`auto`, `cpu` or `cuda`).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Cpu => "cpu",
            Self::Cuda => "cuda",
        }
    }
}

/// How the model's matrix products are computed (a run's `run.matmul`, the `--matmul` flag).
///
/// - `fp32` (the default): IEEE float32, as PyTorch >= 1.12 computes them by default; promptdt's
///   CUDA step matches PyTorch's within the measured tolerances of docs/reproducibility.md.
/// - `tf32`: cuBLAS may use TF32 tensor cores (10-bit mantissa inputs, float32 accumulation) on
///   Ampere and later GPUs: PyTorch's `torch.backends.cuda.matmul.allow_tf32 = True`. This is what
///   the reference code computed on such GPUs: its pinned `torch==1.10.0` had TF32 matmuls on by
///   default (the default became off in PyTorch 1.12). Results differ from `fp32` in about the
///   third significant digit of a product.
///
/// - `bf16`: mixed precision as PyTorch's `torch.autocast(dtype=torch.bfloat16)` computes it, on
///   the CPU or CUDA: the transformer's matrix products (its linear layers and both attention
///   products) take bfloat16 inputs (8-bit mantissa) and accumulate in float32; master weights,
///   gradients' optimiser state, layer norms, softmax and the loss stay float32
///   (`pdt_torch::autocast`). Only where the hardware computes bf16 natively (a CPU with AMX-BF16 or
///   AVX512-BF16, an NVIDIA GPU of compute capability 8.0 or later); elsewhere refused, unless
///   `PROMPTDT_BF16_EMULATED=1` asks for the (slow, but numerically the same) emulation anyway.
///   Experimental: its speed and its fidelity on Cheetah-Dir are not yet measured on native hardware.
///
/// It is one setting of the whole process (libtorch keeps TF32 globally, and the autocast switch is
/// read by every forward pass), so every run of a pack shares it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Matmul {
    #[default]
    Fp32,
    Tf32,
    Bf16,
}

impl std::str::FromStr for Matmul {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "fp32" => Ok(Self::Fp32),
            "tf32" => Ok(Self::Tf32),
            "bf16" => Ok(Self::Bf16),
            other => {
                Err(format!("unknown matmul precision `{other}` (expected fp32, tf32 or bf16)"))
            }
        }
    }
}

impl Matmul {
    /// The name `from_str` takes back (`fp32`, `tf32` or `bf16`).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Fp32 => "fp32",
            Self::Tf32 => "tf32",
            Self::Bf16 => "bf16",
        }
    }

    /// Whether this is the default (`fp32`): configurations at the default do not write it.
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }
}
