//! A pack's inputs stacked on the host and uploaded once ([`PackedBatch::from_host`]).
//!
//! Why: built from the runs' own device batches ([`PackedBatch::new`]), a step of a pack costs each
//! run's uploads (two per segment batch, from the run's thread, beside the engine's kernel launches),
//! a placeholder's five kernels for each run without a prompt, and a `cat` per field. On a GPU the
//! pack's step is bound by the host dispatching its work, so that overhead showed: the pack of 12's
//! step took 13.45 ms in the real loop against 10.8-12.6 ms in the bench, whose batches were already
//! on the device (BENCHMARKS.md, fourth H200 session). Stacked here the same values take four uploads
//! for the whole pack. The tensors are those of [`PackedBatch::new`] value for value (tested).

use super::{PackedBatch, PackedError};
use crate::config::PromptDtConfig;
use crate::prompt_dt::Segments;
use tch::Device;

/// One run's segment batch on the host, `[B, T, ...]` row-major, as [`Segments::from_host`] takes
/// it.
#[derive(Debug, Clone, Copy)]
pub struct HostSegments<'a> {
    pub batch: usize,
    pub steps: usize,
    pub states: &'a [f32],
    pub actions: &'a [f32],
    pub returns_to_go: &'a [f32],
    pub timesteps: &'a [i64],
    pub mask: &'a [f32],
}

impl HostSegments<'_> {
    /// Each field's length against `[batch, steps, dim]`.
    fn check(&self, ds: usize, da: usize) -> Result<(), String> {
        let n = self.batch * self.steps;
        let fields = [
            ("states", self.states.len(), n * ds),
            ("actions", self.actions.len(), n * da),
            ("returns_to_go", self.returns_to_go.len(), n),
            ("timesteps", self.timesteps.len(), n),
            ("mask", self.mask.len(), n),
        ];
        for (name, len, want) in fields {
            if len != want {
                return Err(format!(
                    "`{name}` has {len} values, expected {want} for {} samples of {} steps",
                    self.batch, self.steps
                ));
            }
        }
        if self.steps == 0 {
            return Err("has no steps".into());
        }
        Ok(())
    }
}

/// One run's inputs to a pack step, on the host: its history and, when it uses one, its prompt.
#[derive(Debug, Clone, Copy)]
pub struct HostRow<'a> {
    pub history: HostSegments<'a>,
    pub prompt: Option<HostSegments<'a>>,
}

/// The runs' segments stacked along the samples, each sample's steps left-padded to `steps`.
struct Stack {
    steps: usize,
    ds: usize,
    da: usize,
    states: Vec<f32>,
    actions: Vec<f32>,
    returns_to_go: Vec<f32>,
    timesteps: Vec<i64>,
    mask: Vec<f32>,
}

impl Stack {
    fn new(samples: usize, steps: usize, ds: usize, da: usize) -> Self {
        let n = samples * steps;
        Self {
            steps,
            ds,
            da,
            states: Vec::with_capacity(n * ds),
            actions: Vec::with_capacity(n * da),
            returns_to_go: Vec::with_capacity(n),
            timesteps: Vec::with_capacity(n),
            mask: Vec::with_capacity(n),
        }
    }

    /// `steps` zero steps (timestep 0) with the given mask value, `count` times.
    fn zero_steps(&mut self, count: usize, mask: f32) {
        let n = count;
        self.states.resize(self.states.len() + n * self.ds, 0.0);
        self.actions.resize(self.actions.len() + n * self.da, 0.0);
        self.returns_to_go.resize(self.returns_to_go.len() + n, 0.0);
        self.timesteps.resize(self.timesteps.len() + n, 0);
        self.mask.resize(self.mask.len() + n, mask);
    }

    /// `samples` placeholder samples, as [`PackedBatch::new`]'s (zeros with the given mask).
    fn placeholder(&mut self, samples: usize, mask: f32) {
        self.zero_steps(samples * self.steps, mask);
    }

    /// `s`'s samples, each after `self.steps - s.steps` masked zero steps (as `left_pad`).
    fn push(&mut self, s: &HostSegments<'_>) {
        let (t, ds, da) = (s.steps, self.ds, self.da);
        let pad = self.steps - t;
        for i in 0..s.batch {
            self.zero_steps(pad, 0.0);
            self.states.extend_from_slice(&s.states[i * t * ds..(i + 1) * t * ds]);
            self.actions.extend_from_slice(&s.actions[i * t * da..(i + 1) * t * da]);
            self.returns_to_go.extend_from_slice(&s.returns_to_go[i * t..(i + 1) * t]);
            self.timesteps.extend_from_slice(&s.timesteps[i * t..(i + 1) * t]);
            self.mask.extend_from_slice(&s.mask[i * t..(i + 1) * t]);
        }
    }

    fn upload(self, device: Device) -> Segments {
        let samples = self.mask.len() / self.steps.max(1);
        Segments::from_host(
            samples,
            self.steps,
            self.ds,
            self.da,
            &self.states,
            &self.actions,
            &self.returns_to_go,
            &self.timesteps,
            &self.mask,
            device,
        )
    }
}

impl PackedBatch {
    /// [`Self::new`] from the runs' host batches: the same checks, layout and values, stacked on
    /// the host and uploaded once per field group (see the module documentation).
    pub fn from_host(
        rows: &[Option<HostRow<'_>>],
        batch: i64,
        k: i64,
        p: i64,
        cfg: &PromptDtConfig,
        device: Device,
    ) -> Result<Self, PackedError> {
        let (ds, da) = (cfg.state_dim, cfg.act_dim);
        if rows.iter().all(Option::is_none) {
            return Err(PackedError::Empty);
        }
        let (b, kk, pp) = (batch.max(0) as usize, k.max(0) as usize, p.max(0) as usize);
        let mut history = Stack::new(rows.len() * b, kk, ds, da);
        let mut prompt = Stack::new(rows.len() * b, pp, ds, da);
        let mut prompt_lens = Vec::with_capacity(rows.len());
        for (slot, row) in rows.iter().enumerate() {
            let bad = |what: String| PackedError::Input { slot, what };
            let Some(row) = row else {
                history.placeholder(b, 1.0);
                prompt.placeholder(b, 0.0);
                prompt_lens.push(0);
                continue;
            };
            let h = &row.history;
            h.check(ds, da).map_err(|w| bad(format!("history {w}")))?;
            if h.batch != b || h.steps != kk {
                return Err(bad(format!(
                    "history of {} samples of {} steps, the pack holds {batch} of {k}",
                    h.batch, h.steps
                )));
            }
            history.push(h);
            let lp = match &row.prompt {
                Some(pr) => {
                    if pr.steps > pp {
                        return Err(bad(format!(
                            "prompt of {} steps, the pack holds {p}",
                            pr.steps
                        )));
                    }
                    pr.check(ds, da).map_err(|w| bad(format!("prompt {w}")))?;
                    if pr.batch != b {
                        return Err(bad(format!(
                            "prompt of {} samples, the pack holds {batch}",
                            pr.batch
                        )));
                    }
                    prompt.push(pr);
                    pr.steps as i64
                }
                None => {
                    prompt.placeholder(b, 0.0);
                    0
                }
            };
            if 3 * (lp + k) > cfg.n_positions as i64 {
                return Err(bad(format!(
                    "3 x ({lp} prompt + {k} history steps) tokens exceed n_positions = {}",
                    cfg.n_positions
                )));
            }
            prompt_lens.push(lp);
        }
        Ok(Self {
            history: history.upload(device),
            prompt: (p > 0).then(|| prompt.upload(device)),
            prompt_lens,
            present: rows.iter().map(Option::is_some).collect(),
            batch,
            k,
            p,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::packed::PackedRow;
    use tch::Tensor;

    /// A run's segments on the host, with values that tell samples, steps and fields apart.
    struct Owned {
        batch: usize,
        steps: usize,
        states: Vec<f32>,
        actions: Vec<f32>,
        returns_to_go: Vec<f32>,
        timesteps: Vec<i64>,
        mask: Vec<f32>,
    }

    impl Owned {
        fn new(batch: usize, steps: usize, ds: usize, da: usize, seed: f32) -> Self {
            let n = batch * steps;
            let v = |len: usize, k: f32| (0..len).map(|i| seed + k + i as f32 * 0.25).collect();
            Self {
                batch,
                steps,
                states: v(n * ds, 0.0),
                actions: v(n * da, 100.0),
                returns_to_go: v(n, 200.0),
                timesteps: (0..n as i64).map(|i| i % 7 + seed as i64).collect(),
                // A masked step here and there, as real padded segments have.
                mask: (0..n).map(|i| if i % 5 == 0 { 0.0 } else { 1.0 }).collect(),
            }
        }

        fn host(&self) -> HostSegments<'_> {
            HostSegments {
                batch: self.batch,
                steps: self.steps,
                states: &self.states,
                actions: &self.actions,
                returns_to_go: &self.returns_to_go,
                timesteps: &self.timesteps,
                mask: &self.mask,
            }
        }

        fn device(&self, ds: usize, da: usize) -> Segments {
            Segments::from_host(
                self.batch,
                self.steps,
                ds,
                da,
                &self.states,
                &self.actions,
                &self.returns_to_go,
                &self.timesteps,
                &self.mask,
                Device::Cpu,
            )
        }
    }

    fn same(a: &Tensor, b: &Tensor) -> bool {
        a.size() == b.size() && a.kind() == b.kind() && a.equal(b)
    }

    fn same_segments(a: &Segments, b: &Segments) -> bool {
        same(&a.states, &b.states)
            && same(&a.actions, &b.actions)
            && same(&a.returns_to_go, &b.returns_to_go)
            && same(&a.timesteps, &b.timesteps)
            && same(&a.mask, &b.mask)
    }

    #[test]
    fn host_stacking_equals_the_device_stacking() {
        let cfg = PromptDtConfig::reference(5, 3);
        let (ds, da) = (cfg.state_dim, cfg.act_dim);
        let (b, k, p) = (4usize, 6usize, 5usize);
        // A full prompt, a shorter one (left-padded), none (MT-ORL), and a run not stepped.
        let hist: Vec<Owned> = (0..3).map(|i| Owned::new(b, k, ds, da, i as f32)).collect();
        let prompts =
            [Some(Owned::new(b, p, ds, da, 10.0)), Some(Owned::new(b, 3, ds, da, 20.0)), None];
        let host_rows: Vec<Option<HostRow<'_>>> = (0..4)
            .map(|i| {
                (i < 3).then(|| HostRow {
                    history: hist[i].host(),
                    prompt: prompts[i].as_ref().map(Owned::host),
                })
            })
            .collect();
        let dev_h: Vec<Segments> = hist.iter().map(|h| h.device(ds, da)).collect();
        let dev_p: Vec<Option<Segments>> =
            prompts.iter().map(|p| p.as_ref().map(|p| p.device(ds, da))).collect();
        let dev_rows: Vec<Option<PackedRow<'_>>> = (0..4)
            .map(|i| (i < 3).then(|| PackedRow { history: &dev_h[i], prompt: dev_p[i].as_ref() }))
            .collect();
        let (bi, ki, pi) = (b as i64, k as i64, p as i64);
        let a = PackedBatch::from_host(&host_rows, bi, ki, pi, &cfg, Device::Cpu).unwrap();
        let d = PackedBatch::new(&dev_rows, bi, ki, pi, &cfg, Device::Cpu).unwrap();
        assert!(same_segments(&a.history, &d.history));
        assert!(same_segments(a.prompt.as_ref().unwrap(), d.prompt.as_ref().unwrap()));
        assert_eq!(a.prompt_lens, vec![5, 3, 0, 0]);
        assert_eq!(a.prompt_lens, d.prompt_lens);
        assert_eq!(a.present, d.present);
        assert_eq!((a.batch, a.k, a.p), (d.batch, d.k, d.p));
    }

    fn row<'a>(h: &'a Owned, p: Option<&'a Owned>) -> Option<HostRow<'a>> {
        Some(HostRow { history: h.host(), prompt: p.map(Owned::host) })
    }

    #[test]
    fn bad_host_rows_are_refused_by_slot_and_field() {
        let cfg = PromptDtConfig::reference(5, 3);
        let (ds, da) = (cfg.state_dim, cfg.act_dim);
        let good = Owned::new(2, 4, ds, da, 0.0);
        let mut short = Owned::new(2, 4, ds, da, 0.0);
        short.actions.pop();
        let long_prompt = Owned::new(2, 6, ds, da, 0.0);
        let err = |rows: &[Option<HostRow<'_>>]| {
            PackedBatch::from_host(rows, 2, 4, 5, &cfg, Device::Cpu).unwrap_err().to_string()
        };
        let e = err(&[row(&good, None), row(&short, None)]);
        assert!(e.contains("1") && e.contains("`actions`"), "{e}");
        let e = err(&[row(&good, Some(&long_prompt))]);
        assert!(e.contains("prompt of 6 steps"), "{e}");
        let e = err(&[None, None]);
        assert!(!e.is_empty());
        // A history of the wrong length for the pack.
        let other = Owned::new(2, 3, ds, da, 0.0);
        let e = err(&[row(&other, None)]);
        assert!(e.contains("history of 2 samples of 3 steps"), "{e}");
    }
}
