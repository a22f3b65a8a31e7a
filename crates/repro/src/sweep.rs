//! A sweep's shape on the machine that runs it: runs at once, libtorch threads per run, runs per
//! pack and the packs' engine. The defaults depend on the device; `promptdt reproduce`'s flags
//! override each.

use pdt_base::device::{DeviceSpec, Matmul};
use pdt_rundir::pack::Engine;
use std::path::Path;

/// What the flags asked for; `None` takes the device's default.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SweepAsk {
    pub jobs: Option<usize>,
    pub threads: Option<usize>,
    pub pack: Option<usize>,
    pub pack_engine: Option<Engine>,
}

/// The defaults on one device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SweepDefaults {
    /// The cores the runs share: each of `jobs` runs gets `cores / jobs` threads by default.
    pub cores: usize,
    pub jobs: usize,
    pub pack: usize,
    pub pack_engine: Engine,
}

/// A sweep's shape, every value settled.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sweep {
    pub jobs: usize,
    pub threads: usize,
    pub pack: usize,
    pub pack_engine: Engine,
}

impl SweepDefaults {
    /// The defaults on this machine's cores, on a GPU or on the CPU.
    pub fn for_device(on_gpu: bool) -> Self {
        Self::with_cores(on_gpu, pdt_base::threads::available_cores())
    }

    /// The defaults with `cores` cores. Measured: on 2 cores, 2 runs of 1 thread each finish a set
    /// of runs 1.36x sooner than 1 run of 2 threads (`benchmarks/14-omp-wait-policy.json`), so the
    /// CPU runs one run per core; on an H200 two Cheetah-Dir runs at once made 1.7x the iterations
    /// per hour of one alone, and four no more, so a GPU runs 2. Packing pays on a GPU only: one
    /// batched engine call steps the pack's runs at once (12 runs: 10.5x), while on the CPU a pack
    /// gains nothing over separate processes, so there each run keeps its own process.
    pub fn with_cores(on_gpu: bool, cores: usize) -> Self {
        let cores = cores.max(1);
        Self {
            cores,
            jobs: if on_gpu { 2 } else { cores },
            pack: if on_gpu { 12 } else { 1 },
            pack_engine: Engine::default_for(on_gpu),
        }
    }

    /// The sweep with what was asked in place of the defaults; the threads per run follow the
    /// jobs asked for when they are not given themselves.
    pub fn sweep(&self, ask: &SweepAsk) -> Sweep {
        let jobs = ask.jobs.unwrap_or(self.jobs).max(1);
        Sweep {
            jobs,
            threads: ask.threads.unwrap_or((self.cores / jobs).max(1)),
            pack: ask.pack.unwrap_or(self.pack),
            pack_engine: ask.pack_engine.unwrap_or(self.pack_engine),
        }
    }
}

/// What an emitted job is told, so that it runs as this sweep would here: each job resolves its
/// own device and OpenMP policy, so a sweep emitted with `--device cuda` does not quietly fall
/// back to the CPU on a node without a CUDA libtorch.
#[derive(Debug, Clone, Copy)]
pub struct JobFlags<'a> {
    pub device: DeviceSpec,
    pub matmul: Matmul,
    pub omp_wait_policy: &'a str,
    /// Given only where the sweep was given one (else each job takes `<out>/data`).
    pub data_root: Option<&'a Path>,
    pub pretrained_root: &'a Path,
}

impl Sweep {
    /// The `promptdt reproduce` flags of each emitted job.
    pub fn job_args(&self, j: &JobFlags<'_>) -> Vec<String> {
        let mut args = vec![
            "--threads".to_string(),
            self.threads.to_string(),
            "--device".into(),
            j.device.as_str().into(),
            "--omp-wait-policy".into(),
            j.omp_wait_policy.into(),
        ];
        if j.matmul != Matmul::default() {
            args.extend(["--matmul".into(), j.matmul.as_str().into()]);
        }
        if let Some(d) = j.data_root {
            args.extend(["--data-root".into(), d.to_string_lossy().into_owned()]);
        }
        args.extend(["--pretrained-root".into(), j.pretrained_root.to_string_lossy().into_owned()]);
        if self.pack > 1 {
            args.extend(["--pack".into(), self.pack.to_string()]);
            args.extend(["--pack-engine".into(), self.pack_engine.name().into()]);
        }
        args
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cpu_runs_a_run_per_core_each_in_its_own_process() {
        let d = SweepDefaults::with_cores(false, 8);
        let s = d.sweep(&SweepAsk::default());
        assert_eq!(s, Sweep { jobs: 8, threads: 1, pack: 1, pack_engine: Engine::Solo });
        // Fewer jobs asked for: their runs share the cores.
        let s = d.sweep(&SweepAsk { jobs: Some(3), ..Default::default() });
        assert_eq!((s.jobs, s.threads), (3, 2));
    }

    #[test]
    fn a_gpu_runs_two_packs_of_twelve_with_the_batched_engine() {
        let s = SweepDefaults::with_cores(true, 16).sweep(&SweepAsk::default());
        assert_eq!(s, Sweep { jobs: 2, threads: 8, pack: 12, pack_engine: Engine::Batched });
        let ask = SweepAsk {
            threads: Some(1),
            pack: Some(1),
            pack_engine: Some(Engine::Solo),
            jobs: None,
        };
        let s = SweepDefaults::with_cores(true, 16).sweep(&ask);
        assert_eq!(s, Sweep { jobs: 2, threads: 1, pack: 1, pack_engine: Engine::Solo });
    }

    #[test]
    fn jobs_pass_on_the_flags_they_need_and_no_others() {
        let s = Sweep { jobs: 2, threads: 3, pack: 1, pack_engine: Engine::Solo };
        let j = JobFlags {
            device: DeviceSpec::Cpu,
            matmul: Matmul::default(),
            omp_wait_policy: "PASSIVE",
            data_root: None,
            pretrained_root: Path::new("/p"),
        };
        let args = s.job_args(&j).join(" ");
        assert_eq!(args, "--threads 3 --device cpu --omp-wait-policy PASSIVE --pretrained-root /p");
        let packed = Sweep { pack: 4, pack_engine: Engine::Batched, ..s };
        let args = packed.job_args(&JobFlags { data_root: Some(Path::new("/d")), ..j }).join(" ");
        assert!(
            args.ends_with("--data-root /d --pretrained-root /p --pack 4 --pack-engine batched"),
            "{args}"
        );
    }
}
