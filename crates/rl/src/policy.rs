//! Exported actors: the pretrained experts committed under `pretrained/<family>/`.
//!
//! A policy file is a safetensors file with the actor's layers (`layers.{l}.weight` `[1, in, out]`,
//! `layers.{l}.bias` `[1, 1, out]`, input-major: the transpose of `nn.Linear.weight`) and, in its
//! metadata under `promptdt_policy`, a JSON [`PolicyMeta`]: algorithm, sizes, how raw outputs become
//! actions, and the task encoding of the agent's input.

use crate::agent::{actor_raw, Algorithm, Noise, PolicyHead, TaskEncoder};
use crate::nets::Mlp;
use crate::RlError;
use pdt_base::tensor_file::describe_safetensors_error;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;
use tch::Device;

pub const POLICY_FORMAT: &str = "promptdt-policy-v1";
const META_KEY: &str = "promptdt_policy";

/// What a policy file says about itself.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolicyMeta {
    pub format: String,
    pub algorithm: Algorithm,
    pub family: String,
    /// `[input, hidden.., raw output]`.
    pub sizes: Vec<i64>,
    pub act_dim: usize,
    pub head: PolicyHead,
    pub encoder: TaskEncoder,
    /// Environment steps of training when the actor was saved.
    pub step: u64,
    /// Deterministic evaluation return per task when saved (one entry per task of the family).
    #[serde(default)]
    pub eval_returns: Vec<f64>,
}

/// An actor with everything needed to act in its family.
#[derive(Debug)]
pub struct Policy {
    pub meta: PolicyMeta,
    pub actor: Mlp,
    pub device: Device,
}

impl Policy {
    /// Raw outputs for a batch of environment observations of the given tasks.
    pub fn raw(&self, observations: &[&[f32]], tasks: &[usize]) -> Vec<f32> {
        let mut x = Vec::with_capacity(observations.len() * self.meta.encoder.input_dim());
        for (obs, &task) in observations.iter().zip(tasks) {
            self.meta.encoder.encode(obs, task, &mut x);
        }
        actor_raw(&self.actor, &x, observations.len(), self.device)
    }

    /// Deterministic action for one observation (a convenience for tests and examples).
    pub fn act_deterministic(&self, obs: &[f32], task: usize) -> Vec<f32> {
        let raw = self.raw(&[obs], &[task]);
        let mut out = Vec::with_capacity(self.meta.act_dim);
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        self.meta.head.action(&raw, self.meta.act_dim, Noise::Deterministic, &mut rng, &mut out);
        self.meta.encoder.decode_action(&mut out);
        out
    }
}

/// Writes `actor` with `meta` to `path` atomically.
pub fn save(path: &Path, actor: &Mlp, meta: &PolicyMeta) -> Result<(), RlError> {
    let flat = actor.to_vec();
    let mut named: Vec<(String, Vec<u8>, Vec<usize>)> = Vec::new();
    for (name, off, shape) in actor.named_shapes() {
        let n: i64 = shape.iter().product();
        let vals = &flat[off as usize..(off + n) as usize];
        named.push((
            name,
            vals.iter().flat_map(|v| v.to_le_bytes()).collect(),
            shape.iter().map(|&d| d as usize).collect(),
        ));
    }
    let bad = |message: String| RlError::File { path: path.to_path_buf(), message };
    let views = named
        .iter()
        .map(|(n, bytes, shape)| {
            TensorView::new(Dtype::F32, shape.clone(), bytes).map(|v| (n.clone(), v))
        })
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| bad(e.to_string()))?;
    let meta_json = serde_json::to_string(meta).map_err(|e| bad(e.to_string()))?;
    let metadata = HashMap::from([(META_KEY.to_string(), meta_json)]);
    let bytes = safetensors::serialize(views, &Some(metadata)).map_err(|e| bad(e.to_string()))?;
    crate::write_atomic(path, &bytes)
}

/// Reads a policy file, checking its metadata against its tensors.
pub fn load(path: &Path, device: Device) -> Result<Policy, RlError> {
    let bytes = pdt_base::fs::read_limited(path, pdt_base::fs::MAX_TENSOR_FILE_BYTES)
        .map_err(|source| RlError::Io { path: path.to_path_buf(), source })?;
    from_bytes(&bytes, path, device)
}

/// Parses the bytes of the policy file `path` (named in errors), as [`load`] does.
pub fn from_bytes(bytes: &[u8], path: &Path, device: Device) -> Result<Policy, RlError> {
    let bad = |message: String| RlError::File { path: path.to_path_buf(), message };
    let plain = |e: safetensors::SafeTensorError| {
        bad(format!("not a policy file: {}", describe_safetensors_error(&e, bytes.len())))
    };
    let (_, header) = SafeTensors::read_metadata(bytes).map_err(plain)?;
    let meta_json = header
        .metadata()
        .as_ref()
        .and_then(|m| m.get(META_KEY))
        .ok_or_else(|| bad(format!("no `{META_KEY}` metadata: not a promptdt policy file")))?;
    let meta: PolicyMeta = serde_json::from_str(meta_json)
        .map_err(|e| bad(format!("invalid policy metadata: {e}")))?;
    if meta.format != POLICY_FORMAT {
        return Err(bad(format!("format {:?}, expected {POLICY_FORMAT:?}", meta.format)));
    }
    if meta.sizes.len() < 2 || meta.sizes.iter().any(|s| !(1..=1 << 16).contains(s)) {
        return Err(bad(format!("implausible layer sizes {:?}", meta.sizes)));
    }
    if meta.sizes[0] as usize != meta.encoder.input_dim()
        || *meta.sizes.last().unwrap_or(&0) as usize != meta.head.raw_dim(meta.act_dim)
    {
        return Err(bad(format!(
            "layer sizes {:?} do not fit input {} and output {}",
            meta.sizes,
            meta.encoder.input_dim(),
            meta.head.raw_dim(meta.act_dim)
        )));
    }
    if let Some(m) = &meta.encoder.mirror {
        let feature_dim = meta.encoder.task_features.first().map_or(0, Vec::len);
        if !m.fits(meta.encoder.obs_dim, meta.act_dim, feature_dim) {
            return Err(bad(format!(
                "mirror `{}` does not fit observation {}, action {} and task feature {}",
                m.name, meta.encoder.obs_dim, meta.act_dim, feature_dim
            )));
        }
    }
    let st = SafeTensors::deserialize(bytes).map_err(plain)?;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut actor = Mlp::new(&meta.sizes, 1, &mut rng, Device::Cpu);
    let mut flat = vec![0f32; actor.flat.numel()];
    for (name, off, shape) in actor.named_shapes() {
        let view = st.tensor(&name).map_err(|_| bad(format!("missing tensor `{name}`")))?;
        let want: Vec<usize> = shape.iter().map(|&d| d as usize).collect();
        if view.dtype() != Dtype::F32 || view.shape() != want.as_slice() {
            return Err(bad(format!(
                "tensor `{name}` is {:?} {:?}, expected F32 {want:?}",
                view.dtype(),
                view.shape()
            )));
        }
        for (k, chunk) in view.data().chunks_exact(4).enumerate() {
            let v = f32::from_le_bytes([chunk[0], chunk[1], chunk[2], chunk[3]]);
            if !v.is_finite() {
                return Err(bad(format!("tensor `{name}` has a non-finite value at {k}")));
            }
            flat[off as usize + k] = v;
        }
    }
    actor.load_vec(&flat).map_err(bad)?;
    let actor = if device == Device::Cpu {
        actor
    } else {
        let mut a = actor.detached_copy();
        a.flat = a.flat.to_device(device);
        a
    };
    Ok(Policy { meta, actor, device })
}
