//! `promptdt._native.render`: an environment's current state as an RGB frame, through
//! `pdt_envs::render` (`docs/rendering.md`). Conversion only: the renderer, cameras and checks
//! live in pdt-envs.

use crate::errors::{InvalidInputError, StateError};
use numpy::{PyArray3, PyArrayMethods, ToPyArray};
use pyo3::prelude::*;

use pdt_envs::render::{FrameSize, RenderError};

use crate::envs::VecEnv;

/// gymnasium's MuJoCo environments render 480 x 480 by default.
const DEFAULT_SIZE: usize = 480;

fn render_error(e: RenderError) -> PyErr {
    match e {
        // A bad argument; everything else (no GL context, a renderer failure) is the machine's.
        RenderError::Size { .. } => InvalidInputError::new_err(e.to_string()),
        other => StateError::new_err(other.to_string()),
    }
}

/// Renders environment `index` of `env` as a `[height, width, 3]` uint8 array (top row first).
#[pyfunction]
#[pyo3(signature = (env, index, width = DEFAULT_SIZE, height = DEFAULT_SIZE))]
pub(crate) fn render<'py>(
    py: Python<'py>,
    env: &Bound<'py, VecEnv>,
    index: usize,
    width: usize,
    height: usize,
) -> PyResult<Bound<'py, PyArray3<u8>>> {
    let size = FrameSize::new(width, height).map_err(render_error)?;
    let env = env.get();
    let n = env.with_venv(|venv| venv.len())?;
    if index >= n {
        return Err(InvalidInputError::new_err(format!(
            "index: {index}, expected 0..{n} (num_envs)"
        )));
    }
    let frame = py.detach(|| env.with_venv(|venv| venv.render(index, size)))?;
    let frame = frame.map_err(render_error)?;
    let flat = frame.rgb.to_pyarray(py);
    flat.reshape([frame.height, frame.width, 3])
        .map_err(|e| InvalidInputError::new_err(e.to_string()))
}
