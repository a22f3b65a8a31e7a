//! Prompt-DT's token layout: each step is three tokens, `(R_t, s_t, a_t)`, so the trunk's
//! positions 1, 4, 7, ... are the state tokens, whose outputs the action head reads.

use tch::Tensor;

/// The state tokens' rows (positions 1, 4, 7, ... of the `(R, s, a)` interleaving) along the
/// second-to-last dimension, as a view: `[..., L, D]` -> `[..., L/3, D]` (`L` a multiple of 3).
pub fn state_rows(t: &Tensor) -> Tensor {
    let mut shape = t.size();
    let d = shape.len().saturating_sub(2);
    let l = shape.get(d).copied().unwrap_or(0);
    shape.splice(d..=d, [l / 3, 3]);
    t.view(shape.as_slice()).select(d as i64 + 1, 1) // splitting a dimension is always a view
}
