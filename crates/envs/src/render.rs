//! Offscreen rendering of an environment's current state as an RGB frame (`docs/rendering.md`).
//!
//! The MuJoCo families are drawn by MuJoCo's own renderer (`mjv_updateScene`, `mjr_render`,
//! `mjr_readPixels`, through mujoco-rs's `MjRenderer`) into an offscreen framebuffer of a headless
//! OpenGL context from EGL (Mesa's device platform: a GPU where there is one, else its software
//! rasteriser llvmpipe; no display, no window). glutin opens `libEGL.so.1` at run time (dlopen), so
//! every binary and the Python wheel start on a machine without it: only rendering then fails, with
//! [`RenderError::NoContext`] naming the Debian packages to install (`scripts/setup_render.sh`).
//! The point robot is not a MuJoCo scene: its frame is drawn here, a 2-D top view.
//!
//! Which camera draws a family lives with the family: its [`Env::view`] returns the simulator
//! state and a [`Camera`]. Rendering reads that state and changes nothing: an episode is the same
//! with or without frames taken.
//!
//! Threads. A GL context is current on one thread at a time, so each thread keeps its own renderer
//! (built on its first frame, rebuilt when the frame size changes) in a thread-local.

use std::cell::RefCell;
use std::sync::Arc;

use mujoco_rs::prelude::{MjData, MjModel, MjvCamera};
use mujoco_rs::renderer::MjRenderer;

use crate::{Env, EnvError};

/// The Debian packages that give MuJoCo a headless GL context (what `scripts/setup_render.sh`
/// installs): the EGL loader, Mesa's EGL vendor library, its DRI drivers (llvmpipe) and GBM.
pub const GL_PACKAGES: &str = "libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1";

/// How a family's scene is looked at.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Camera {
    /// A camera of the model (by id), as the model defines it (e.g. the cheetah's `track`).
    Model { id: usize },
    /// Follows body `body` (its id): looks at it from `distance` metres, at `azimuth` and
    /// `elevation` degrees, whatever it does.
    Tracking { body: usize, distance: f64, azimuth: f64, elevation: f64 },
    /// Looks at the fixed point `lookat` from `distance` metres, at `azimuth`/`elevation` degrees.
    Fixed { lookat: [f64; 3], distance: f64, azimuth: f64, elevation: f64 },
}

impl Camera {
    fn mjv(self) -> MjvCamera {
        match self {
            Camera::Model { id } => MjvCamera::new_fixed(id),
            Camera::Tracking { body, distance, azimuth, elevation } => {
                let mut c = MjvCamera::new_tracking(body);
                (c.distance, c.azimuth, c.elevation) = (distance, azimuth, elevation);
                c
            }
            Camera::Fixed { lookat, distance, azimuth, elevation } => {
                let mut c = MjvCamera::new_user();
                c.type_ = mujoco_rs::prelude::MjtCamera::mjCAMERA_FREE as i32;
                (c.lookat, c.distance, c.azimuth, c.elevation) =
                    (lookat, distance, azimuth, elevation);
                c
            }
        }
    }
}

/// What a renderer needs to draw an environment now ([`Env::view`]).
pub enum View<'a> {
    /// A MuJoCo scene: the simulation (read only: `mjv_updateScene` takes it mutably but changes
    /// no state) and the family's camera.
    Mujoco { data: &'a mut MjData<Arc<MjModel>>, camera: Camera },
    /// A point in a square arena seen from above (the point robot).
    Plane(Plane),
}

/// A 2-D top view: the agent's and the goal's positions in a square `[-extent, extent]^2`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    pub position: [f32; 2],
    pub goal: Option<[f32; 2]>,
    pub extent: f32,
}

/// The size of a frame in pixels, checked: both at least 1 and at most [`MAX_WIDTH`] x
/// [`MAX_HEIGHT`] (the models' offscreen framebuffer, MuJoCo's default 640 x 480).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameSize {
    width: usize,
    height: usize,
}

/// Largest frame width: the MuJoCo models' offscreen buffer (`<visual><global offwidth>`).
pub const MAX_WIDTH: usize = 640;
/// Largest frame height (`offheight`).
pub const MAX_HEIGHT: usize = 480;

impl FrameSize {
    pub fn new(width: usize, height: usize) -> Result<Self, RenderError> {
        if width == 0 || height == 0 || width > MAX_WIDTH || height > MAX_HEIGHT {
            return Err(RenderError::Size { width, height });
        }
        Ok(Self { width, height })
    }

    pub fn width(self) -> usize {
        self.width
    }

    pub fn height(self) -> usize {
        self.height
    }
}

/// One RGB frame: `height` rows of `width` pixels of 3 bytes, top row first.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
}

impl Frame {
    /// A frame of one colour.
    pub fn filled(size: FrameSize, color: [u8; 3]) -> Self {
        let n = size.width * size.height;
        Self { width: size.width, height: size.height, rgb: color.repeat(n) }
    }

    /// Sets pixel (x, y) (0, 0 is the top left); outside the frame: nothing.
    pub fn put(&mut self, x: i64, y: i64, color: [u8; 3]) {
        if x < 0 || y < 0 || x as usize >= self.width || y as usize >= self.height {
            return;
        }
        let i = (y as usize * self.width + x as usize) * 3;
        self.rgb[i..i + 3].copy_from_slice(&color);
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error(
        "frame size {width}x{height}: width must be 1..={MAX_WIDTH} and height 1..={MAX_HEIGHT} \
         (the MuJoCo models' offscreen buffer)"
    )]
    Size { width: usize, height: usize },
    /// No headless OpenGL context: EGL (or Mesa's drivers behind it) is missing or refused.
    #[error(
        "cannot open a headless OpenGL context through EGL ({detail}). Rendering needs Mesa's EGL: \
         on Debian/Ubuntu `sudo apt-get install -y --no-install-recommends {GL_PACKAGES}` (or run \
         scripts/setup_render.sh from the promptdt repository)"
    )]
    NoContext { detail: String },
    #[error("{0}")]
    Env(#[from] EnvError),
    #[error("MuJoCo renderer: {0}")]
    Renderer(String),
}

thread_local! {
    /// This thread's renderer and the frame size it was built for (module docs, "Threads").
    static RENDERER: RefCell<Option<(FrameSize, MjRenderer)>> = const { RefCell::new(None) };
}

/// Renders `env`'s current state at `size` (module docs). Families that cannot be drawn answer
/// [`EnvError::Unsupported`].
pub fn render(env: &mut dyn Env, size: FrameSize) -> Result<Frame, RenderError> {
    match env.view()? {
        View::Plane(plane) => Ok(draw_plane(&plane, size)),
        View::Mujoco { data, camera } => RENDERER.with(|cell| {
            let mut slot = cell.borrow_mut();
            let renderer = match &mut *slot {
                Some((built, r)) if *built == size => r,
                _ => {
                    // Drop the old renderer (its context) before making the next one.
                    *slot = None;
                    let r = build(data.model(), size)?;
                    &mut slot.insert((size, r)).1
                }
            };
            renderer.set_camera(camera.mjv());
            renderer.sync_data(data).map_err(|e| describe(&e))?;
            renderer.render().map_err(|e| describe(&e))?;
            let rgb =
                renderer.rgb_flat().ok_or_else(|| RenderError::Renderer("no RGB buffer".into()))?;
            Ok(Frame { width: size.width, height: size.height, rgb: rgb.to_vec() })
        }),
    }
}

fn build(model: &MjModel, size: FrameSize) -> Result<MjRenderer, RenderError> {
    let global = &model.vis().global;
    // The models keep MuJoCo's default buffer; checked so that a model with a smaller one says so.
    if size.width > global.offwidth as usize || size.height > global.offheight as usize {
        return Err(RenderError::Size { width: size.width, height: size.height });
    }
    MjRenderer::builder().width(size.width as u32).height(size.height as u32).build(model).map_err(
        |e| match e {
            mujoco_rs::renderer::RendererError::GlutinError(g) => {
                RenderError::NoContext { detail: chain(&g) }
            }
            other => describe(&other),
        },
    )
}

/// A renderer error with its causes (mujoco-rs's own text names only the outermost).
fn describe(e: &dyn std::error::Error) -> RenderError {
    RenderError::Renderer(chain(e))
}

/// `e: its source: its source's source ...`.
fn chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        text.push_str(": ");
        text.push_str(&c.to_string());
        cause = c.source();
    }
    text
}

/// The point robot's frame: a light arena with a grid, the goal as a red ring, the robot as a
/// blue disc.
fn draw_plane(plane: &Plane, size: FrameSize) -> Frame {
    let mut f = Frame::filled(size, [245, 245, 240]);
    let (w, h) = (size.width as f32, size.height as f32);
    let scale = 0.5 * w.min(h) / plane.extent;
    let to_px = |p: [f32; 2]| (0.5 * w + p[0] * scale, 0.5 * h - p[1] * scale);
    // Grid lines every 0.5 units, the axes darker.
    let mut g = -plane.extent;
    while g <= plane.extent + 1e-6 {
        let (gx, gy) = to_px([g, g]);
        let shade = if g.abs() < 1e-6 { [170, 170, 170] } else { [220, 220, 215] };
        for i in 0..size.width.max(size.height) as i64 {
            f.put(gx.round() as i64, i, shade);
            f.put(i, gy.round() as i64, shade);
        }
        g += 0.5;
    }
    let r = (0.04 * w.min(h)).max(2.0);
    if let Some(goal) = plane.goal {
        let (cx, cy) = to_px(goal);
        disc(&mut f, cx, cy, r * 1.6, Some(r * 0.9), [210, 40, 40]);
    }
    let (cx, cy) = to_px(plane.position);
    disc(&mut f, cx, cy, r, None, [30, 80, 200]);
    f
}

/// Fills the disc of radius `r` around (cx, cy), or the ring between `inner` and `r`.
fn disc(f: &mut Frame, cx: f32, cy: f32, r: f32, inner: Option<f32>, color: [u8; 3]) {
    let ri = inner.unwrap_or(-1.0);
    let (x0, x1) = ((cx - r).floor() as i64, (cx + r).ceil() as i64);
    let (y0, y1) = ((cy - r).floor() as i64, (cy + r).ceil() as i64);
    for y in y0..=y1 {
        for x in x0..=x1 {
            let d = ((x as f32 + 0.5 - cx).powi(2) + (y as f32 + 0.5 - cy).powi(2)).sqrt();
            if d <= r && d >= ri {
                f.put(x, y, color);
            }
        }
    }
}
