//! Normal samples from uniform ones, written out once.
//!
//! Box-Muller rather than `rand_distr`: the dependency set stays small, the algorithm is visible,
//! and data generated from a seed then depends only on rand's uniform sampling (fixed within a
//! rand major version). The functions take the uniform source as a closure so `pdt-base` needs no
//! RNG crate; callers pass `|| rng.random::<f64>()`.

use std::f64::consts::TAU;

/// The radius `sqrt(-2 ln u1)` of a Box-Muller pair, for `u` in `[0, 1)` as rand draws it.
fn radius(u: f64) -> f64 {
    // `1 - u` is in (0, 1], so the logarithm is finite.
    let u1 = 1.0 - u;
    (-2.0 * u1.ln()).sqrt()
}

/// One standard normal sample: draws two uniforms in `[0, 1)` from `uniform` (first the radius's,
/// then the angle's) and returns the cosine branch of Box-Muller.
pub fn standard_normal(mut uniform: impl FnMut() -> f64) -> f64 {
    let r = radius(uniform());
    let u2 = uniform();
    r * (TAU * u2).cos()
}

/// Two independent standard normal samples from the same two uniform draws as
/// [`standard_normal`]: `(cosine branch, sine branch)`. The cosine branch equals what
/// [`standard_normal`] returns for the same draws, bit for bit.
pub fn standard_normal_pair(mut uniform: impl FnMut() -> f64) -> (f64, f64) {
    let r = radius(uniform());
    let u2 = uniform();
    let (s, c) = (TAU * u2).sin_cos();
    (r * c, r * s)
}

/// `n` standard normals as f32, both branches of each pair used (cosine first); an odd `n` drops
/// the last sine branch, so `n` samples always take `2 * ceil(n / 2)` uniform draws.
pub fn standard_normals_f32(mut uniform: impl FnMut() -> f64, n: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(n + 1);
    while out.len() < n {
        let (c, s) = standard_normal_pair(&mut uniform);
        out.push(c as f32);
        out.push(s as f32);
    }
    out.truncate(n);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The uniforms a test feeds in, in order.
    fn feed(values: &[f64]) -> impl FnMut() -> f64 + '_ {
        let mut it = values.iter();
        move || *it.next().unwrap_or(&0.5)
    }

    #[test]
    fn matches_the_closed_form_and_draws_radius_first() {
        let (u1, u2) = (0.25f64, 0.125f64);
        let want = (-2.0 * (1.0 - u1).ln()).sqrt() * (TAU * u2).cos();
        assert_eq!(standard_normal(feed(&[u1, u2])).to_bits(), want.to_bits());
        // Swapping the draws gives another number: the order is part of the contract.
        assert_ne!(standard_normal(feed(&[u2, u1])), want);
    }

    #[test]
    fn pair_cosine_branch_is_the_single_sample() {
        for (u1, u2) in [(0.0f64, 0.0f64), (0.3, 0.7), (0.999, 0.5), (0.5, 0.999_999)] {
            let single = standard_normal(feed(&[u1, u2]));
            let (c, s) = standard_normal_pair(feed(&[u1, u2]));
            assert_eq!(single.to_bits(), c.to_bits());
            let want_s = (-2.0 * (1.0 - u1).ln()).sqrt() * (TAU * u2).sin();
            assert_eq!(s.to_bits(), want_s.to_bits());
        }
    }

    #[test]
    fn zero_uniform_gives_a_finite_sample() {
        assert!(standard_normal(feed(&[0.0, 0.0])).is_finite());
    }

    #[test]
    fn odd_count_uses_whole_pairs() {
        let draws = [0.1, 0.2, 0.3, 0.4];
        let mut used = 0;
        let mut it = draws.iter();
        let v = standard_normals_f32(
            || {
                used += 1;
                *it.next().unwrap_or(&0.5)
            },
            3,
        );
        assert_eq!(v.len(), 3);
        assert_eq!(used, 4);
        let (c0, s0) = standard_normal_pair(feed(&[0.1, 0.2]));
        let (c1, _) = standard_normal_pair(feed(&[0.3, 0.4]));
        assert_eq!(v, vec![c0 as f32, s0 as f32, c1 as f32]);
    }
}
