//! Helpers shared by the `native_*` integration tests: deterministic datasets and hand-built
//! safetensors files (valid, or broken in one chosen way).

#![allow(dead_code)] // each test crate uses a different subset
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use std::collections::HashMap;

use pdt_data::{TaskDataset, Trajectory};
use safetensors::tensor::{Dtype, TensorView};

/// A trajectory whose values depend on `seed`, with the given flags at its last step.
pub fn traj(
    obs_dim: usize,
    act_dim: usize,
    len: usize,
    seed: u32,
    terminated: bool,
    truncated: bool,
) -> Trajectory {
    let val = |i: usize, k: u32| ((i as f32) * 0.37 + (seed * 7 + k) as f32 * 1.13).sin() * 3.0;
    let observations = (0..len * obs_dim).map(|i| val(i, 1)).collect();
    let actions = (0..len * act_dim).map(|i| val(i, 2).clamp(-1.0, 1.0)).collect();
    let rewards = (0..len).map(|i| val(i, 3) - 0.5).collect();
    let mut term = vec![false; len];
    let mut trunc = vec![false; len];
    term[len - 1] = terminated;
    trunc[len - 1] = truncated;
    Trajectory::new(obs_dim, act_dim, observations, actions, rewards, term, trunc)
        .expect("valid test trajectory")
}

/// Four episodes of different lengths covering every flag combination at the last step.
pub fn sample_dataset(obs_dim: usize, act_dim: usize) -> TaskDataset {
    TaskDataset::new(vec![
        traj(obs_dim, act_dim, 7, 1, false, true),
        traj(obs_dim, act_dim, 1, 2, true, false),
        traj(obs_dim, act_dim, 12, 3, true, true),
        traj(obs_dim, act_dim, 5, 4, false, false),
    ])
    .expect("valid test dataset")
}

/// One tensor of a hand-built file.
#[derive(Clone, Debug)]
pub struct RawTensor {
    pub name: String,
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub data: Vec<u8>,
}

impl RawTensor {
    pub fn f32(name: &str, shape: Vec<usize>, values: &[f32]) -> Self {
        let data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        Self { name: name.into(), dtype: Dtype::F32, shape, data }
    }
    pub fn u8(name: &str, values: &[u8]) -> Self {
        Self { name: name.into(), dtype: Dtype::U8, shape: vec![values.len()], data: values.into() }
    }
    pub fn i64(name: &str, values: &[i64]) -> Self {
        let data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        Self { name: name.into(), dtype: Dtype::I64, shape: vec![values.len()], data }
    }
}

/// The six tensors of a valid file holding `ds`, built independently of the crate's writer.
pub fn tensors_of(ds: &TaskDataset) -> Vec<RawTensor> {
    let cat = |f: &dyn Fn(&Trajectory) -> Vec<f32>| -> Vec<f32> {
        ds.trajectories.iter().flat_map(f).collect()
    };
    let flags = |f: &dyn Fn(&Trajectory) -> &Vec<bool>| -> Vec<u8> {
        ds.trajectories.iter().flat_map(|t| f(t).iter().map(|&b| b as u8)).collect()
    };
    let n = ds.num_steps();
    let mut starts = vec![0i64];
    for t in &ds.trajectories {
        starts.push(starts[starts.len() - 1] + t.len() as i64);
    }
    vec![
        RawTensor::f32("observations", vec![n, ds.obs_dim], &cat(&|t| t.observations.clone())),
        RawTensor::f32("actions", vec![n, ds.act_dim], &cat(&|t| t.actions.clone())),
        RawTensor::f32("rewards", vec![n], &cat(&|t| t.rewards.clone())),
        RawTensor::u8("terminated", &flags(&|t| &t.terminated)),
        RawTensor::u8("truncated", &flags(&|t| &t.truncated)),
        RawTensor::i64("episode_starts", &starts),
    ]
}

/// The standard metadata map.
pub fn standard_meta() -> HashMap<String, String> {
    [
        ("format", "promptdt-trajectories"),
        ("format_version", "1"),
        ("env", "cheetah_vel"),
        ("task_index", "2"),
        ("mode", "expert"),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_owned(), v.to_owned()))
    .collect()
}

/// Serialises tensors with the safetensors crate (each tensor self-consistent: bytes = shape x
/// dtype; the tensors may disagree with each other).
pub fn safetensors_bytes(tensors: &[RawTensor], meta: Option<HashMap<String, String>>) -> Vec<u8> {
    let views: Vec<(String, TensorView<'_>)> = tensors
        .iter()
        .map(|t| {
            let v = TensorView::new(t.dtype, t.shape.clone(), &t.data).expect("consistent tensor");
            (t.name.clone(), v)
        })
        .collect();
    safetensors::serialize(views, &meta).expect("serialize")
}

/// Replaces the tensor named `name`.
pub fn replace(tensors: &mut [RawTensor], new: RawTensor) {
    let slot = tensors.iter_mut().find(|t| t.name == new.name).expect("tensor present");
    *slot = new;
}

/// The full message of an error, including its wrapped sources' text.
pub fn message(e: &pdt_data::DataError) -> String {
    e.to_string()
}
