//! A prompted policy's episode as an animated GIF (`promptdt render`, `docs/rendering.md`): the
//! run's policy acts on one task, prompted as its evaluation prompts it, and every state of the
//! episode is rendered ([`pdt_envs::render`]) with the return so far drawn in the corner.
//!
//! Here, beside its one caller, rather than in the policy runtime: filming is a use of a policy,
//! like serving, and its GIF encoder and bitmap font ([`font`]) are needed by nothing else (the
//! Python package's `render` returns bare frames from `pdt_envs::render`).

// Errors carry the policy's (with the offending path or value); returned on the cold path only.
#![allow(clippy::result_large_err)]

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

mod font;

use font::{draw_text, text_width};
use pdt_base::device::DeviceSpec;
use pdt_envs::render::{render, Frame, FrameSize, RenderError};
use pdt_policy::{Policy, PolicyError};

/// What to film (checked by [`VideoConfig::new`]).
#[derive(Debug, Clone)]
pub struct VideoConfig {
    /// The run directory (its latest checkpoint acts).
    pub run: PathBuf,
    /// Where the run's data moved, if it did (prompts are drawn from it).
    pub data: Option<PathBuf>,
    pub device: Option<DeviceSpec>,
    /// The task acted on (an index of the run's family).
    pub task: usize,
    /// The `.gif` written.
    pub out: PathBuf,
    pub size: FrameSize,
    /// Frames a second (1..=100: GIF delays are in hundredths of a second).
    pub fps: u32,
    /// At most this many steps (`None`: the whole episode, up to the family's horizon).
    pub max_steps: Option<usize>,
    /// Seeds the environment's reset and the prompt's draw.
    pub seed: u64,
}

/// What [`record_episode`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoSummary {
    pub out: PathBuf,
    pub family: String,
    pub task: usize,
    /// Steps taken (the GIF has one frame more: the start).
    pub steps: usize,
    pub frames: usize,
    /// The episode's undiscounted return.
    pub ret: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    #[error("{0}")]
    Input(String),
    #[error(transparent)]
    Policy(#[from] PolicyError),
    #[error(transparent)]
    Env(#[from] pdt_envs::EnvError),
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error("{}: {message}", path.display())]
    Write { path: PathBuf, message: String },
}

impl VideoConfig {
    /// Checks what can be checked before the run is loaded: the output is a `.gif` in an existing
    /// directory, the size and the frame rate.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        run: PathBuf,
        task: usize,
        out: PathBuf,
        width: usize,
        height: usize,
        fps: u32,
        max_steps: Option<usize>,
        seed: u64,
    ) -> Result<Self, VideoError> {
        let size = FrameSize::new(width, height)?;
        let is_gif = out.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
        if is_gif.as_deref() != Some("gif") {
            return Err(VideoError::Input(format!(
                "--out {}: only animated GIF (.gif) is written (mp4 would need a system encoder)",
                out.display()
            )));
        }
        let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        if !parent.is_dir() {
            return Err(VideoError::Input(format!(
                "--out {}: directory {} does not exist",
                out.display(),
                parent.display()
            )));
        }
        if !(1..=100).contains(&fps) {
            return Err(VideoError::Input(format!("--fps {fps}: expected 1..=100")));
        }
        if max_steps == Some(0) {
            return Err(VideoError::Input("--max-steps 0: expected at least 1".into()));
        }
        Ok(Self { run, data: None, device: None, task, out, size, fps, max_steps, seed })
    }
}

/// Loads the run, plays one episode of its policy on `cfg.task` and writes it as a GIF.
pub fn record_episode(cfg: &VideoConfig) -> Result<VideoSummary, VideoError> {
    let policy = Policy::load(&cfg.run, cfg.device, cfg.data.as_deref())?;
    // Film the policy that is evaluated, or nothing: an MT-BC-Finetune checkpoint acting as
    // saved would be its multi-task weights, never scored on a test task.
    policy.check_acts_as_evaluated("render")?;
    let family = pdt_envs::family(&policy.env)?;
    let mut env = family.make(cfg.task)?;
    let prompt = if policy.method.uses_prompt() {
        Some(policy.task_prompt(cfg.task, cfg.seed)?)
    } else {
        None
    };
    let prefix = prompt.as_ref().map(|p| policy.prefix(&[p])).transpose()?;
    let limit = cfg.max_steps.unwrap_or(usize::MAX).min(env.horizon());

    let mut gif = GifWriter::create(&cfg.out, cfg.size, cfg.fps)?;
    let obs = env.reset(cfg.seed);
    let mut episode = policy.start(policy.observation(&widen(&obs))?, policy.target(None)?);
    gif.frame(caption(render(env.as_mut(), cfg.size)?, 0.0, 0))?;
    let mut steps = 0;
    loop {
        let action = policy.act(&[&episode], prefix.as_ref());
        episode.accept(&action)?;
        let r = env.step(&action)?;
        steps += 1;
        let ret = episode.ret() + f64::from(r.reward);
        gif.frame(caption(render(env.as_mut(), cfg.size)?, ret, steps))?;
        if r.terminated || r.truncated || steps >= limit {
            gif.finish()?;
            return Ok(VideoSummary {
                out: cfg.out.clone(),
                family: family.name().to_string(),
                task: cfg.task,
                steps,
                frames: steps + 1,
                ret,
            });
        }
        let step = policy.step(f64::from(r.reward), policy.observation(&widen(&r.obs))?)?;
        policy.record(&mut episode, step)?;
    }
}

fn widen(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x)).collect()
}

/// The return so far in the top-left corner, the step in the top-right; the font grows with the
/// frame (1 pixel a font pixel below 200 pixels wide).
fn caption(mut f: Frame, ret: f64, t: usize) -> Frame {
    let scale = (f.width / 200).max(1);
    draw_text(&mut f, 1, 1, scale, &format!("R={ret:.1}"), [255, 230, 90]);
    let t_text = format!("t={t}");
    let x = f.width.saturating_sub(text_width(&t_text, scale) + 2 * scale + 1);
    draw_text(&mut f, x, 1, scale, &t_text, [230, 230, 230]);
    f
}

/// An animated GIF written frame by frame, all frames in one global palette of [`COLOURS`]
/// colours, learnt (NeuQuant) from the first frame: a scene keeps its colours from frame to frame,
/// and fewer, stable colours compress about twice as well as a 256-colour palette per frame.
struct GifWriter {
    file: Option<BufWriter<File>>,
    encoder: Option<(gif::Encoder<BufWriter<File>>, color_quant::NeuQuant)>,
    path: PathBuf,
    size: FrameSize,
    delay: u16,
}

/// Colours of a GIF's palette.
const COLOURS: usize = 64;

impl GifWriter {
    fn create(path: &Path, size: FrameSize, fps: u32) -> Result<Self, VideoError> {
        let file = File::create(path)
            .map_err(|e| VideoError::Write { path: path.into(), message: e.to_string() })?;
        let delay = (100 / fps).max(1) as u16;
        Ok(Self { file: Some(BufWriter::new(file)), encoder: None, path: path.into(), size, delay })
    }

    fn err(&self, e: impl std::fmt::Display) -> VideoError {
        VideoError::Write { path: self.path.clone(), message: e.to_string() }
    }

    fn frame(&mut self, f: Frame) -> Result<(), VideoError> {
        let rgba: Vec<u8> = f.rgb.chunks_exact(3).flat_map(|p| [p[0], p[1], p[2], 255]).collect();
        if self.encoder.is_none() {
            let file = self.file.take().ok_or_else(|| self.err("written twice"))?;
            // Sample factor 10: NeuQuant's default trade of time for palette quality.
            let quant = color_quant::NeuQuant::new(10, COLOURS, &rgba);
            // FrameSize caps both at 640, well inside u16.
            let (w, h) = (self.size.width() as u16, self.size.height() as u16);
            let mut encoder =
                gif::Encoder::new(file, w, h, &quant.color_map_rgb()).map_err(|e| self.err(e))?;
            encoder.set_repeat(gif::Repeat::Infinite).map_err(|e| self.err(e))?;
            self.encoder = Some((encoder, quant));
        }
        let Some((encoder, quant)) = self.encoder.as_mut() else {
            return Err(self.err("no encoder"));
        };
        let indices: Vec<u8> = rgba.chunks_exact(4).map(|p| quant.index_of(p) as u8).collect();
        let mut g = gif::Frame::from_indexed_pixels(f.width as u16, f.height as u16, indices, None);
        g.delay = self.delay;
        let written = encoder.write_frame(&g);
        written.map_err(|e| self.err(e))
    }

    fn finish(self) -> Result<(), VideoError> {
        let Some((encoder, _)) = self.encoder else {
            return Err(VideoError::Write { path: self.path, message: "no frame".into() });
        };
        let path = self.path;
        let err = |message: String| VideoError::Write { path: path.clone(), message };
        let mut w = encoder.into_inner().map_err(|e| err(e.to_string()))?;
        std::io::Write::flush(&mut w).map_err(|e| err(e.to_string()))
    }
}
