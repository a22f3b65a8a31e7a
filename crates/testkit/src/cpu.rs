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
    // Another MKL or oneDNN path ([`KERNEL_PATH_ENV`]): not measured as batch-invariant, and under
    // `MKL_CBWR=COMPATIBLE` a row alone and in a batch differ by up to 2.2e-7 (AMD EPYC).
    if ["MKL_CBWR", "MKL_ENABLE_INSTRUCTIONS", "ONEDNN_MAX_CPU_ISA"]
        .iter()
        .any(|v| std::env::var_os(v).is_some())
    {
        return false;
    }
    if let Ok(v) = std::env::var("ATEN_CPU_CAPABILITY") {
        if matches!(v.to_ascii_lowercase().as_str(), "avx2" | "default") {
            return true;
        }
    }
    CpuFingerprint::detect().is_none_or(|f| f.aten_capability() != "AVX512")
}

/// Largest relative difference allowed between an episode return evaluated now and one committed
/// from another CPU (`testdata/rundir-v1`'s `eval_final.json`). Measured on the fixture's two runs
/// (20-step point-robot episodes, so closed-loop drift is short): Prompt-DT up to 2.6e-8 on an
/// Intel Xeon with AVX-512 against the AMD EPYC (AVX2) that made them, and up to 1.1e-7 on that AMD
/// under `ATEN_CPU_CAPABILITY=default`; MACAW, whose evaluation takes gradient steps first, up to
/// 1.1e-6 under `MKL_CBWR=COMPATIBLE` (2026-12-06). About ten times the largest.
pub const CROSS_CPU_RETURN_REL: f64 = 1e-5;

/// The environment variables [`KERNEL_PATH_ENV`] sets: another code path in each of libtorch's
/// three kernel sources (ATen's vectorised kernels, MKL's sgemm, oneDNN), on any x86 CPU. Each was
/// checked to change the bits of some operation on an AMD EPYC with AVX2 (matmul, softmax, layer
/// norm under `ATEN_CPU_CAPABILITY=default`; matmul under `MKL_CBWR=COMPATIBLE`; GELU under
/// `ONEDNN_MAX_CPU_ISA=SSE41`). `scripts/test_other_kernels.sh` runs the tests that read numbers
/// committed from another machine under them, so a bitwise assumption against such numbers fails
/// on the machine where the test is written, not first on a user's CPU.
pub const KERNEL_PATH_ENV: &[(&str, &str)] = &[
    ("ATEN_CPU_CAPABILITY", "default"),
    ("MKL_CBWR", "COMPATIBLE"),
    ("ONEDNN_MAX_CPU_ISA", "SSE41"),
];

/// Compares two JSON documents: the same shape, keys and non-numeric values exactly, integers
/// exactly, and other numbers within `rel` of `want` (relative; absolute below 1). `Err` names the
/// first difference by its path (`tasks[2].returns[0]`). For results made now against results
/// committed from another CPU, whose floats may differ in their last bits.
pub fn json_close(
    got: &serde_json::Value,
    want: &serde_json::Value,
    rel: f64,
) -> Result<(), String> {
    json_close_at("$", got, want, rel)
}

fn json_close_at(
    at: &str,
    got: &serde_json::Value,
    want: &serde_json::Value,
    rel: f64,
) -> Result<(), String> {
    use serde_json::Value;
    match (got, want) {
        (Value::Number(g), Value::Number(w)) if w.is_f64() || g.is_f64() => {
            let (g, w) = (g.as_f64().unwrap_or(f64::NAN), w.as_f64().unwrap_or(f64::NAN));
            let diff = (g - w).abs();
            if diff <= rel * w.abs().max(1.0) {
                Ok(())
            } else {
                Err(format!(
                    "{at}: {g} against {w} (difference {diff:e}, allowed {rel:e} relative)"
                ))
            }
        }
        (Value::Array(g), Value::Array(w)) if g.len() == w.len() => g
            .iter()
            .zip(w)
            .enumerate()
            .try_for_each(|(i, (g, w))| json_close_at(&format!("{at}[{i}]"), g, w, rel)),
        (Value::Object(g), Value::Object(w))
            if g.keys().collect::<Vec<_>>() == w.keys().collect::<Vec<_>>() =>
        {
            g.iter()
                .zip(w)
                .try_for_each(|((k, g), (_, w))| json_close_at(&format!("{at}.{k}"), g, w, rel))
        }
        _ if got == want => Ok(()),
        _ => Err(format!("{at}: {got} against {want}")),
    }
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

    #[test]
    fn json_close_allows_last_bits_and_names_the_first_difference() {
        let want = serde_json::json!({"n": 3, "tasks": [{"r": -22.777376651763916, "s": "a"}]});
        let near = serde_json::json!({"n": 3, "tasks": [{"r": -22.777377247810364, "s": "a"}]});
        assert_eq!(json_close(&near, &want, CROSS_CPU_RETURN_REL), Ok(()));
        assert!(json_close(&near, &want, 0.0).unwrap_err().starts_with("$.tasks[0].r: "));
        let far = serde_json::json!({"n": 3, "tasks": [{"r": -22.8, "s": "a"}]});
        assert!(json_close(&far, &want, CROSS_CPU_RETURN_REL).is_err());
        let other_int =
            serde_json::json!({"n": 4, "tasks": [{"r": -22.777376651763916, "s": "a"}]});
        assert_eq!(json_close(&other_int, &want, 1.0), Err("$.n: 4 against 3".into()));
        let other_str =
            serde_json::json!({"n": 3, "tasks": [{"r": -22.777376651763916, "s": "b"}]});
        assert!(json_close(&other_str, &want, 1.0).is_err());
        let shorter = serde_json::json!({"n": 3, "tasks": []});
        assert!(json_close(&shorter, &want, 1.0).is_err());
    }
}
