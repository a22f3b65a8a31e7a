//! Offscreen rendering of every family (`pdt_envs::render`): frames have the asked size, are not
//! blank, follow the state, and leave the episode unchanged.
//!
//! With `PROMPTDT_RENDER_DOCS=<dir>` the test also writes one PNG per family there (the frames of
//! `docs/rendering.md`, 320x240, after 30 steps of a fixed action pattern).

use pdt_envs::render::{render, Frame, FrameSize, RenderError};
use pdt_envs::{family, Env, FAMILY_NAMES};

fn size(w: usize, h: usize) -> FrameSize {
    FrameSize::new(w, h).unwrap_or_else(|e| panic!("{e}"))
}

fn frame(env: &mut dyn Env, s: FrameSize) -> Frame {
    render(env, s).unwrap_or_else(|e| panic!("render: {e}"))
}

/// A deterministic, varied action (so the body moves).
fn action(t: usize, dim: usize) -> Vec<f32> {
    (0..dim).map(|i| (0.3 * t as f32 + 1.7 * i as f32).sin()).collect()
}

fn distinct_colours(f: &Frame) -> usize {
    let mut seen: Vec<&[u8]> = f.rgb.chunks(3).collect();
    seen.sort_unstable();
    seen.dedup();
    seen.len()
}

#[test]
fn every_family_renders_frames_that_change_and_leave_the_episode_alone() {
    let docs = std::env::var_os("PROMPTDT_RENDER_DOCS").map(std::path::PathBuf::from);
    for name in FAMILY_NAMES {
        let fam = family(name).unwrap_or_else(|e| panic!("{e}"));
        let mut env = fam.make(0).unwrap_or_else(|e| panic!("{e}"));
        let mut twin = fam.make(0).unwrap_or_else(|e| panic!("{e}"));
        env.reset(5);
        twin.reset(5);
        let s = size(96, 72);
        let first = frame(env.as_mut(), s);
        assert_eq!((first.width, first.height, first.rgb.len()), (96, 72, 96 * 72 * 3), "{name}");
        assert!(distinct_colours(&first) > 3, "{name}: the first frame is (nearly) one colour");
        let mut last = first.clone();
        let mut changed = 0;
        for t in 0..10 {
            let a = action(t, env.act_dim());
            let r = env.step(&a).unwrap_or_else(|e| panic!("{name}: {e}"));
            let r_twin = twin.step(&a).unwrap_or_else(|e| panic!("{name}: {e}"));
            // Rendering reads the state only: the rendered env steps as its twin does.
            assert_eq!(r, r_twin, "{name}: rendering changed the episode at step {t}");
            let f = frame(env.as_mut(), s);
            changed += usize::from(f != last);
            last = f;
        }
        assert!(changed >= 5, "{name}: only {changed} of 10 frames changed");
        // Another size rebuilds this thread's renderer.
        let big = frame(env.as_mut(), size(160, 120));
        assert_eq!(big.rgb.len(), 160 * 120 * 3, "{name}");
        if let Some(dir) = &docs {
            write_doc_frame(dir, name, fam.as_ref());
        }
    }
}

#[test]
fn a_bad_size_is_refused_naming_the_limits() {
    for (w, h) in [(0, 10), (10, 0), (641, 100), (100, 481)] {
        let err = FrameSize::new(w, h).expect_err("refused");
        assert!(matches!(err, RenderError::Size { .. }), "{err}");
        let text = err.to_string();
        assert!(text.contains(&format!("{w}x{h}")) && text.contains("640"), "{text}");
    }
}

fn write_doc_frame(dir: &std::path::Path, name: &str, fam: &dyn pdt_envs::EnvFamily) {
    let mut env = fam.make(0).unwrap_or_else(|e| panic!("{e}"));
    env.reset(1);
    for t in 0..30 {
        if env.step(&action(t, env.act_dim())).is_err() {
            break;
        }
    }
    let f = frame(env.as_mut(), size(320, 240));
    let path = dir.join(format!("{name}.png"));
    let file = std::fs::File::create(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), 320, 240);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().unwrap_or_else(|e| panic!("{e}"));
    w.write_image_data(&f.rgb).unwrap_or_else(|e| panic!("{e}"));
}

#[test]
fn a_vec_env_renders_each_environment_on_its_own_thread() {
    use pdt_envs::vec_env::VecEnv;
    let fam = family("cheetah_vel").unwrap_or_else(|e| panic!("{e}"));
    let envs = (0..3).map(|t| fam.make(t).unwrap_or_else(|e| panic!("{e}"))).collect();
    // Three threads: environments 1 and 2 live on workers, 0 on the calling thread.
    let mut venv = VecEnv::new(envs, 3);
    venv.reset(&[1, 2, 3]).unwrap_or_else(|e| panic!("{e}"));
    let mut alone = fam.make(2).unwrap_or_else(|e| panic!("{e}"));
    alone.reset(3);
    let s = size(64, 48);
    let frames: Vec<Frame> =
        (0..3).map(|i| venv.render(i, s).unwrap_or_else(|e| panic!("env {i}: {e}"))).collect();
    // Same task and seed, rendered on this thread instead of a worker: the same picture.
    assert_eq!(frames[2], frame(alone.as_mut(), s));
    assert_ne!(frames[0], frames[1], "different seeds should give different poses");
    let err = venv.render(3, s).expect_err("no environment 3");
    assert!(err.to_string().contains("environment 3 of 3"), "{err}");
}

/// Without libEGL the process still runs and a frame fails naming the packages to install. The
/// library is hidden by bind-mounting /dev/null over it in a private mount namespace (`unshare
/// -m`, root only); where that is not possible the test says so and checks nothing.
#[test]
fn without_egl_a_frame_fails_naming_the_debian_packages() {
    if std::env::var_os("PROMPTDT_RENDER_NO_EGL_CHILD").is_some() {
        let fam = family("cheetah_vel").unwrap_or_else(|e| panic!("{e}"));
        let mut env = fam.make(0).unwrap_or_else(|e| panic!("{e}"));
        let Err(err) = render(env.as_mut(), size(32, 24)) else {
            panic!("libEGL is hidden, yet a MuJoCo frame was rendered");
        };
        assert!(matches!(err, RenderError::NoContext { .. }), "{err}");
        assert!(err.to_string().contains(pdt_envs::render::GL_PACKAGES), "{err}");
        // The drawn family needs no GL.
        let mut point =
            family("point_robot").and_then(|f| f.make(0)).unwrap_or_else(|e| panic!("{e}"));
        assert!(render(point.as_mut(), size(32, 24)).is_ok());
        return;
    }
    let Ok(lib) = std::fs::canonicalize("/usr/lib/x86_64-linux-gnu/libEGL.so.1") else {
        return eprintln!("skipped: no /usr/lib/x86_64-linux-gnu/libEGL.so.1 to hide");
    };
    let exe = std::env::current_exe().unwrap_or_else(|e| panic!("{e}"));
    let out = std::process::Command::new("unshare")
        .args(["-m", "sh", "-c", "mount --bind /dev/null \"$1\" && exec \"$2\" --exact \"$3\""])
        .arg("sh")
        .arg(&lib)
        .arg(&exe)
        // Its name in the test binary: the module path less the crate's name (`render::..`).
        .arg(format!(
            "{}::without_egl_a_frame_fails_naming_the_debian_packages",
            module_path!().split_once("::").map_or("", |(_, m)| m)
        ))
        .env("PROMPTDT_RENDER_NO_EGL_CHILD", "1")
        .output();
    let out = match out {
        Ok(o) => o,
        Err(e) => return eprintln!("skipped: cannot run unshare ({e})"),
    };
    let text =
        format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    if !out.status.success() && (text.contains("unshare:") || text.contains("mount:")) {
        return eprintln!("skipped: no private mount namespace here: {text}");
    }
    assert!(out.status.success() && text.contains("1 passed"), "{text}");
}
