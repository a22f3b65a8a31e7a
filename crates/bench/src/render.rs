//! `render_<family>_<W>x<H>`: the cost of one rendered frame (`pdt_envs::render`) of a family at
//! W x H pixels: MuJoCo's scene update, drawing and the pixel read-back, on this thread's headless
//! GL context (llvmpipe on a machine without a GPU). promptdt only (PyTorch renders nothing).
//! Each iteration steps the environment with a fixed action pattern, then times one frame; the
//! first frame (the GL context's creation) is part of the warm-up.

use pdt_envs::render::{render, FrameSize};

/// `(family, width, height)` of a render case, or `None` if `name` is not one.
pub fn parse_case(name: &str) -> Option<(&'static str, usize, usize)> {
    let rest = name.strip_prefix("render_")?;
    let family = pdt_envs::FAMILY_NAMES
        .iter()
        .copied()
        .find(|f| rest.strip_prefix(f).is_some_and(|r| r.starts_with('_')))?;
    let (w, h) = rest[family.len() + 1..].split_once('x')?;
    Some((family, w.parse().ok()?, h.parse().ok()?))
}

/// Milliseconds per frame, `iters` frames after `warmup` (at least 1: the context's creation).
pub fn time_frames(
    family: &str,
    width: usize,
    height: usize,
    warmup: usize,
    iters: usize,
) -> Result<Vec<f64>, String> {
    let size = FrameSize::new(width, height).map_err(|e| e.to_string())?;
    let fam = pdt_envs::family(family).map_err(|e| e.to_string())?;
    let mut env = fam.make(0).map_err(|e| e.to_string())?;
    env.reset(0);
    let mut ms = Vec::with_capacity(iters);
    for i in 0..warmup.max(1) + iters {
        let a: Vec<f32> =
            (0..env.act_dim()).map(|j| (0.3 * i as f32 + 1.7 * j as f32).sin()).collect();
        if env.step(&a).is_err() {
            // The episode ended: start another (not timed).
            env.reset(i as u64);
        }
        let start = std::time::Instant::now();
        let frame = render(env.as_mut(), size).map_err(|e| e.to_string())?;
        let t = start.elapsed().as_secs_f64() * 1e3;
        std::hint::black_box(&frame);
        if i >= warmup.max(1) {
            ms.push(t);
        }
    }
    Ok(ms)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn render_cases_name_a_family_and_a_size() {
        assert_eq!(parse_case("render_cheetah_vel_320x240"), Some(("cheetah_vel", 320, 240)));
        assert_eq!(parse_case("render_point_robot_64x48"), Some(("point_robot", 64, 48)));
        for bad in ["render_walker_1x1", "render_dial_32", "render_dial_ax2", "render_", "dial"] {
            assert_eq!(parse_case(bad), None, "{bad}");
        }
    }
}
