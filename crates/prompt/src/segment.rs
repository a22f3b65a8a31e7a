//! Cutting one segment out of a trajectory, exactly as the reference's `get_batch` / `get_prompt`
//! do it (`promptdt-reference.md` b.4, b.5): left padding, masks, returns-to-go, timesteps.

use crate::normalize::StateNorm;
use pdt_data::Trajectory;

/// Padding values of training batches (`get_batch`): actions are padded with -10 (states with 0
/// before normalisation, returns-to-go and timesteps with 0). The mask hides them from attention,
/// and the loss skips them.
pub const ACTION_PAD: f32 = -10.0;

/// Where to write one segment of `len` steps inside a batch's flat arrays.
pub struct SegmentOut<'a> {
    pub states: &'a mut [f32],
    pub actions: &'a mut [f32],
    pub returns_to_go: &'a mut [f32],
    pub timesteps: &'a mut [i64],
    pub mask: &'a mut [f32],
}

/// Returns-to-go of a trajectory from step `si`: `rtg[t] = sum(rewards[si + t ..])`, accumulated in
/// f32 from the end as the reference's `discount_cumsum(x, 1.0)` on float32 rewards.
pub fn returns_to_go_from(traj: &Trajectory, si: usize, n: usize) -> Vec<f32> {
    let rewards = &traj.rewards[si..];
    let mut rtg = vec![0f32; rewards.len()];
    let mut acc = 0f32;
    for (t, &r) in rewards.iter().enumerate().rev() {
        acc += r;
        rtg[t] = acc;
    }
    rtg.truncate(n);
    rtg
}

/// Writes steps `si .. si + tlen` of `traj` (`tlen = min(len, T - si)`) into `out`, left-padded to
/// `len` steps. States are normalised, returns-to-go divided by `rtg_scale`, timesteps clipped to
/// `max_ep_len - 1`. With `zero_returns`, the returns-to-go are written as 0 (Prompt-MT-BC).
#[allow(clippy::too_many_arguments)] // mirrors the reference's arguments; called from one place
pub fn write_segment(
    traj: &Trajectory,
    si: usize,
    len: usize,
    norm: &StateNorm,
    rtg_scale: f32,
    max_ep_len: usize,
    zero_returns: bool,
    out: SegmentOut<'_>,
) {
    let (ds, da) = (traj.obs_dim, traj.act_dim);
    let tlen = len.min(traj.len() - si);
    let pad = len - tlen;
    let rtg = returns_to_go_from(traj, si, tlen);
    for p in 0..pad {
        for j in 0..ds {
            out.states[p * ds + j] = norm.apply(j, 0.0);
        }
        out.actions[p * da..(p + 1) * da].fill(ACTION_PAD);
        out.returns_to_go[p] = 0.0;
        out.timesteps[p] = 0;
        out.mask[p] = 0.0;
    }
    for (t, &rtg_t) in rtg.iter().enumerate().take(tlen) {
        let (row, src) = (pad + t, si + t);
        for (j, &x) in traj.obs(src).iter().enumerate() {
            out.states[row * ds + j] = norm.apply(j, x);
        }
        out.actions[row * da..(row + 1) * da].copy_from_slice(traj.action(src));
        // The reference divides float64 (after padding with float64 zeros) and casts to float32.
        out.returns_to_go[row] =
            if zero_returns { 0.0 } else { (rtg_t as f64 / rtg_scale as f64) as f32 };
        out.timesteps[row] = src.min(max_ep_len - 1) as i64;
        out.mask[row] = 1.0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn traj(t: usize) -> Trajectory {
        let obs = (0..t * 2).map(|i| i as f32).collect();
        let act = (0..t).map(|i| i as f32 / 100.0).collect();
        let rew = (0..t).map(|i| (i + 1) as f32).collect();
        Trajectory::new(2, 1, obs, act, rew, vec![false; t], vec![false; t]).unwrap()
    }

    struct Buf {
        s: Vec<f32>,
        a: Vec<f32>,
        r: Vec<f32>,
        t: Vec<i64>,
        m: Vec<f32>,
    }

    fn cut(
        tr: &Trajectory,
        si: usize,
        len: usize,
        norm: &StateNorm,
        clip: usize,
        zero: bool,
    ) -> Buf {
        let mut b = Buf {
            s: vec![9.; len * 2],
            a: vec![9.; len],
            r: vec![9.; len],
            t: vec![9; len],
            m: vec![9.; len],
        };
        let out = SegmentOut {
            states: &mut b.s,
            actions: &mut b.a,
            returns_to_go: &mut b.r,
            timesteps: &mut b.t,
            mask: &mut b.m,
        };
        write_segment(tr, si, len, norm, 10.0, clip, zero, out);
        b
    }

    #[test]
    fn full_segment_has_suffix_returns_and_original_timesteps() {
        let tr = traj(6); // rewards 1..6, total 21
        let b = cut(&tr, 1, 3, &StateNorm::identity(2), 1000, false);
        assert_eq!(b.m, vec![1.0; 3]);
        assert_eq!(b.t, vec![1, 2, 3]);
        assert_eq!(b.r, vec![2.0, 1.8, 1.5]); // (20, 18, 15) / 10
        assert_eq!(b.s, vec![2., 3., 4., 5., 6., 7.]);
        assert_eq!(b.a, vec![0.01, 0.02, 0.03]);
    }

    #[test]
    fn segment_past_the_end_is_left_padded() {
        let tr = traj(6);
        let norm = StateNorm { mean: vec![1.0, 2.0], std: vec![2.0, 4.0] };
        let b = cut(&tr, 4, 4, &norm, 1000, false);
        assert_eq!(b.m, vec![0., 0., 1., 1.]);
        assert_eq!(b.t, vec![0, 0, 4, 5]);
        assert_eq!(b.a, vec![ACTION_PAD, ACTION_PAD, 0.04, 0.05]);
        assert_eq!(b.r, vec![0.0, 0.0, 1.1, 0.6]); // (5 + 6, 6) / 10

        // pads are normalised zeros: -mean/std
        assert_eq!(&b.s[..4], &[-0.5, -0.5, -0.5, -0.5]);
        assert_eq!(&b.s[4..6], &[(8.0 - 1.0) / 2.0, (9.0 - 2.0) / 4.0]);
    }

    #[test]
    fn timesteps_are_clipped_and_returns_can_be_zeroed() {
        let tr = traj(6);
        let b = cut(&tr, 2, 4, &StateNorm::identity(2), 4, true);
        assert_eq!(b.t, vec![2, 3, 3, 3]);
        assert_eq!(b.r, vec![0.0; 4]);
    }

    #[test]
    fn returns_to_go_accumulate_in_f32_from_the_end() {
        let tr = Trajectory::new(
            1,
            1,
            vec![0.; 3],
            vec![0.; 3],
            vec![0.1, 0.2, 0.3],
            vec![false; 3],
            vec![false; 3],
        )
        .unwrap();
        let rtg = returns_to_go_from(&tr, 0, 3);
        assert_eq!(rtg, vec![0.3f32 + 0.2f32 + 0.1f32, 0.3f32 + 0.2f32, 0.3f32]);
    }
}
