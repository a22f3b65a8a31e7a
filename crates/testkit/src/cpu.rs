//! Which CPU kernels libtorch will run: the fingerprint that decides whether two float results can be
//! compared bit for bit.
//!
//! libtorch (ATen's `DEFAULT`/`AVX2`/`AVX512` kernels, MKL's sgemm, oneDNN) picks its code paths at
//! run time from the processor's vendor and instruction set. Two machines with the same fingerprint
//! run the same kernels, so the same libtorch build, thread count and seed give the same bits; two
//! machines with different fingerprints may differ in the last bits of every matmul and reduction.
//! `scripts/golden/make_prompt_dt_fixtures.py` records the same fingerprint (read the same way from
//! `/proc/cpuinfo`) beside the parity fixtures, and the parity tests compare bitwise only when the
//! fingerprints are equal (testdata/golden/README.md).

use serde::{Deserialize, Serialize};

/// The `/proc/cpuinfo` flags that change which kernels libtorch, MKL or oneDNN dispatch to, in this
/// order. Python's fixture writer keeps the same list: change both together.
pub const KERNEL_FLAGS: &[&str] = &[
    "sse4_2",
    "avx",
    "avx2",
    "fma",
    "f16c",
    "avx512f",
    "avx512dq",
    "avx512cd",
    "avx512bw",
    "avx512vl",
    "avx512_vnni",
    "avx512_bf16",
    "avx512_fp16",
    "avx512vbmi",
    "avx_vnni",
    "amx_tile",
    "amx_bf16",
    "amx_int8",
];

/// Vendor, model and kernel-relevant instruction-set flags of a CPU.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CpuFingerprint {
    /// `vendor_id` (`GenuineIntel`, `AuthenticAMD`): MKL takes other paths on other vendors.
    pub vendor_id: String,
    /// `model name` (cache sizes, which MKL's blocking depends on, follow the model).
    pub model_name: String,
    /// The [`KERNEL_FLAGS`] this CPU has, in that order.
    pub isa: Vec<String>,
}

impl CpuFingerprint {
    /// This machine's fingerprint, from `/proc/cpuinfo`; `None` where there is no such file (not
    /// Linux) or it names no processor.
    pub fn detect() -> Option<Self> {
        std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|t| Self::from_cpuinfo(&t))
    }

    /// Parses the first processor block of a `/proc/cpuinfo` text.
    pub fn from_cpuinfo(text: &str) -> Option<Self> {
        let field = |key: &str| {
            text.lines()
                .filter_map(|l| l.split_once(':'))
                .find(|(k, _)| k.trim() == key)
                .map(|(_, v)| v.trim().to_string())
        };
        let vendor_id = field("vendor_id")?;
        let flags = field("flags").unwrap_or_default();
        let have: std::collections::HashSet<&str> = flags.split_whitespace().collect();
        let isa =
            KERNEL_FLAGS.iter().filter(|f| have.contains(**f)).map(|f| (*f).to_string()).collect();
        Some(Self { vendor_id, model_name: field("model name").unwrap_or_default(), isa })
    }

    /// The widest vector extension, as libtorch names its kernel sets (`AVX512`, `AVX2`, `DEFAULT`).
    pub fn aten_capability(&self) -> &'static str {
        let has = |f: &str| self.isa.iter().any(|x| x == f);
        if ["avx512f", "avx512bw", "avx512vl", "avx512dq"].iter().all(|f| has(f)) {
            "AVX512"
        } else if has("avx2") && has("fma") {
            "AVX2"
        } else {
            "DEFAULT"
        }
    }
}

impl std::fmt::Display for CpuFingerprint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} / {} [{}]", self.vendor_id, self.model_name, self.isa.join(" "))
    }
}

/// Largest difference allowed between a row computed alone and the same row computed in a batch,
/// where [`batch_invariant`] does not hold (measured: at most 3e-7 on actions).
pub const BATCH_TOLERANCE: f32 = 1e-6;

/// Whether, with one libtorch thread, a row's result is the same bits whatever batch it is computed
/// in. Measured: yes where libtorch runs its AVX2 kernels (AMD EPYC, 2026-11), and on an earlier
/// AVX-512 CPU; no on an Intel Xeon with AVX-512 VNNI/VBMI2 (2026-11-24: a policy's actions alone
/// and batched differ by up to 3e-7). So this answers yes for AVX2 kernels only; tests of batching
/// compare bit for bit where it holds and within [`BATCH_TOLERANCE`] elsewhere. `ATEN_CPU_CAPABILITY=avx2` (or `default`)
/// makes libtorch use the narrower kernels, and then this holds again.
pub fn batch_invariant() -> bool {
    if let Ok(v) = std::env::var("ATEN_CPU_CAPABILITY") {
        if matches!(v.to_ascii_lowercase().as_str(), "avx2" | "default") {
            return true;
        }
    }
    CpuFingerprint::detect().is_none_or(|f| f.aten_capability() != "AVX512")
}

#[cfg(test)]
mod tests {
    use super::*;

    const AMD: &str = "processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC\n\
        flags\t\t: fpu sse4_2 fma avx avx2 f16c\n\nprocessor\t: 1\nvendor_id\t: Other\n";
    const INTEL: &str = "vendor_id : GenuineIntel\nmodel name : Intel(R) Xeon(R) Platinum 8480+\n\
        flags : avx avx2 fma avx512f avx512dq avx512bw avx512vl avx512_vnni amx_tile\n";

    #[test]
    fn parses_the_first_processor_and_keeps_the_kernel_flags_in_order() {
        let c = CpuFingerprint::from_cpuinfo(AMD).expect("parsed");
        assert_eq!(c.vendor_id, "AuthenticAMD");
        assert_eq!(c.model_name, "AMD EPYC");
        assert_eq!(c.isa, ["sse4_2", "avx", "avx2", "fma", "f16c"]);
        assert_eq!(c.aten_capability(), "AVX2");
        let i = CpuFingerprint::from_cpuinfo(INTEL).expect("parsed");
        assert_eq!(i.aten_capability(), "AVX512");
        assert_ne!(c, i);
        assert!(CpuFingerprint::from_cpuinfo("nothing here").is_none());
    }

    #[test]
    fn round_trips_through_json() {
        let c = CpuFingerprint::from_cpuinfo(INTEL).expect("parsed");
        let back: CpuFingerprint =
            serde_json::from_str(&serde_json::to_string(&c).expect("json")).expect("parsed");
        assert_eq!(back, c);
    }
}
