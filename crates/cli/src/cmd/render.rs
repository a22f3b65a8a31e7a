//! `promptdt render`: a prompted episode of a run's policy as an animated GIF.

use crate::args::RenderArgs;
use anyhow::Result;

pub fn render(a: RenderArgs) -> Result<()> {
    let mut cfg = crate::video::VideoConfig::new(
        a.run,
        a.task,
        a.out,
        a.width,
        a.height,
        a.fps,
        a.max_steps,
        a.seed,
    )?;
    (cfg.device, cfg.data) = (a.device, a.data);
    let v = crate::video::record_episode(&cfg)?;
    // Formatted here: the video's summary moves with the video code out of pdt-policy.
    out!(
        "{}: {} task {}, {} steps, return {:.2} ({} frames)",
        v.out.display(),
        v.family,
        v.task,
        v.steps,
        v.ret,
        v.frames
    );
    Ok(())
}
