//! MACAW's buffers: the derived fields of the official writer (spec 2.2), the `end` mode with its
//! stride (2.3), the two batch draws (2.4), and clear errors for data that cannot serve.
#![allow(clippy::unwrap_used)]

use pdt_data::{TaskDataset, Trajectory};
use pdt_macaw::{BufferSpec, TaskBuffer};
use rand::SeedableRng;
use tch::Device;

/// An episode of `n` steps whose observation at step t is [t, e] and reward t + 1.
fn episode(n: usize, e: f32) -> Trajectory {
    let obs: Vec<f32> = (0..n).flat_map(|t| [t as f32, e]).collect();
    let act: Vec<f32> = (0..n).map(|t| t as f32 / n as f32).collect();
    let rew: Vec<f32> = (0..n).map(|t| t as f32 + 1.0).collect();
    let mut trunc = vec![false; n];
    trunc[n - 1] = true;
    Trajectory::new(2, 1, obs, act, rew, vec![false; n], trunc).unwrap()
}

fn spec(rows: usize, skip: usize, reverse: bool) -> BufferSpec {
    BufferSpec { rows, skip, reverse_episodes: reverse, discount: 0.99 }
}

#[test]
fn derived_fields_of_a_200_step_episode() {
    let ds = TaskDataset::new(vec![episode(200, 0.0)]).unwrap();
    let b = TaskBuffer::from_dataset("t", &ds, &spec(0, 1, false)).unwrap();
    assert_eq!(b.len(), 200);
    let (obs0, _, s_t, k0, g0) = b.row(0);
    assert_eq!(obs0, [0.0, 0.0]);
    // s_T: the episode's last stored observation (promptdt stores no final next-observation)
    assert_eq!(s_t, [199.0, 0.0]);
    assert_eq!(k0, 0.99f64.powi(200) as f32);
    let want: f64 = (0..200).map(|k| 0.99f64.powi(k) * (k as f64 + 1.0)).sum();
    assert_eq!(g0, want as f32);
    let (_, _, _, k199, g199) = b.row(199);
    assert_eq!(k199, 0.99f32);
    assert_eq!(g199, 200.0, "G_199 = r_199");
}

#[test]
fn episodes_are_stored_reversed_and_cut_like_the_official_end_mode() {
    let ds = TaskDataset::new(vec![episode(10, 0.0), episode(10, 1.0)]).unwrap();
    let rev = TaskBuffer::from_dataset("t", &ds, &spec(0, 1, true)).unwrap();
    // episode 0 backwards, then episode 1 backwards
    let firsts: Vec<[f32; 2]> = (0..20).map(|r| [rev.row(r).0[0], rev.row(r).0[1]]).collect();
    assert_eq!(firsts[0], [9.0, 0.0]);
    assert_eq!(firsts[9], [0.0, 0.0]);
    assert_eq!(firsts[10], [9.0, 1.0]);
    // reversed rows keep their own fields: the row of step 9 has kappa = gamma^1, G = r_9
    assert_eq!(rev.row(0).3, 0.99f32);
    assert_eq!(rev.row(0).4, 10.0);
    // the last 12 rows, every 7th: rows 8 and 15 of the 20
    let cut = TaskBuffer::from_dataset("t", &ds, &spec(12, 7, true)).unwrap();
    assert_eq!(cut.len(), 2);
    assert_eq!(cut.row(0), rev.row(8));
    assert_eq!(cut.row(1), rev.row(15));
}

#[test]
fn batches_are_contiguous_windows_or_distinct_rows() {
    let ds = TaskDataset::new((0..5).map(|e| episode(20, e as f32)).collect()).unwrap();
    let b = TaskBuffer::from_dataset("t", &ds, &spec(0, 1, false)).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    for _ in 0..50 {
        let w = b.sample(16, true, &mut rng, Device::Cpu).unwrap();
        let g: Vec<f32> = Vec::try_from(w.mc_return.view([-1])).unwrap();
        // consecutive rows of the buffer: find the window's start by its first row
        let start = (0..b.len()).find(|&r| (0..16).all(|i| b.row(r + i).4 == g[i])).unwrap();
        assert!(start + 16 < b.len(), "the last window is never drawn (randint(0, n - B))");
        let u = b.sample(100, false, &mut rng, Device::Cpu).unwrap();
        let obs: Vec<f32> = Vec::try_from(u.obs.view([-1])).unwrap();
        let mut keys: Vec<(i64, i64)> = obs.chunks(2).map(|c| (c[0] as i64, c[1] as i64)).collect();
        keys.sort_unstable();
        keys.dedup();
        assert_eq!(keys.len(), 100, "uniform rows are drawn without replacement");
    }
}

#[test]
fn too_little_data_and_non_finite_returns_are_named_errors() {
    let ds = TaskDataset::new(vec![episode(10, 0.0)]).unwrap();
    let b = TaskBuffer::from_dataset("cheetah_vel-3", &ds, &spec(0, 1, true)).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let e = b.sample(10, true, &mut rng, Device::Cpu).unwrap_err().to_string();
    assert!(
        e.contains("cheetah_vel-3") && e.contains("10 transitions") && e.contains("at least 11"),
        "{e}"
    );
    assert!(b.sample(10, false, &mut rng, Device::Cpu).is_ok());
    let e = b.sample(11, false, &mut rng, Device::Cpu).unwrap_err().to_string();
    assert!(e.contains("uniform batch of 11"), "{e}");
    let mut t = episode(10, 0.0);
    t.rewards[3] = 3e38;
    t.rewards[4] = 3e38;
    let ds = TaskDataset::new(vec![t]).unwrap();
    let e = TaskBuffer::from_dataset("ant_dir-6", &ds, &spec(0, 1, true)).unwrap_err().to_string();
    assert!(e.contains("ant_dir-6") && e.contains("not finite"), "{e}");
}
