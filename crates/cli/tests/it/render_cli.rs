//! `promptdt render`: a tiny trained run's prompted episode as a GIF that
//! decodes with one frame per state, and the arguments it refuses.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{fails, ok, s, tiny_setup};

/// Frames and their size in the GIF at `path`.
fn gif_frames(path: &std::path::Path) -> (usize, u16, u16) {
    let mut options = gif::DecodeOptions::new();
    options.set_color_output(gif::ColorOutput::RGBA);
    let mut d = options.read_info(std::fs::File::open(path).unwrap()).unwrap();
    let (w, h) = (d.width(), d.height());
    let mut n = 0;
    while d.read_next_frame().unwrap().is_some() {
        n += 1;
    }
    (n, w, h)
}

#[test]
fn render_writes_a_gif_of_a_prompted_episode() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("run");
    ok(&["train", "--config", s(&cfg), "--out", s(&run), "--quiet"]);
    let gif = tmp.path().join("episode.gif");
    let msg = ok(&[
        "render",
        "--run",
        s(&run),
        "--task",
        "34",
        "--out",
        s(&gif),
        "--width",
        "64",
        "--height",
        "48",
        "--fps",
        "10",
    ]);
    // The point robot's episodes last its horizon, 20 steps: 21 frames with the start.
    assert!(msg.contains("point_robot task 34, 20 steps") && msg.contains("(21 frames)"), "{msg}");
    assert_eq!(gif_frames(&gif), (21, 64, 48));
    let short = tmp.path().join("short.gif");
    let msg =
        ok(&["render", "--run", s(&run), "--task", "34", "--out", s(&short), "--max-steps", "5"]);
    assert!(msg.contains("5 steps"), "{msg}");
    assert_eq!(gif_frames(&short), (6, 160, 120));

    let e =
        fails(&["render", "--run", s(&run), "--task", "34", "--out", s(&tmp.path().join("a.mp4"))]);
    assert!(e.contains("a.mp4") && e.contains(".gif"), "{e}");
    let e =
        fails(&["render", "--run", s(&run), "--task", "34", "--out", s(&gif), "--width", "1000"]);
    assert!(e.contains("frame size 1000x120"), "{e}");
    let e = fails(&["render", "--run", s(&run), "--task", "99", "--out", s(&gif)]);
    assert!(e.contains("task 99"), "{e}");
    let missing = tmp.path().join("nope").join("x.gif");
    let e = fails(&["render", "--run", s(&run), "--task", "34", "--out", s(&missing)]);
    assert!(e.contains("does not exist"), "{e}");
}

/// An MT-BC-Finetune run is evaluated after fine-tuning its multi-task weights on each test
/// task's demonstrations; its checkpoint acting as saved is another policy. `render` refused
/// MACAW but filmed such a run from its multi-task weights: now it refuses it, with the
/// check and the message `serve` uses (one owner: `Policy::check_acts_as_evaluated`).
#[test]
fn render_and_serve_refuse_a_run_that_fine_tunes_before_it_acts() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("finetune");
    ok(&["train", "--config", s(&cfg), "--out", s(&run), "--method", "mt-bc-finetune", "--quiet"]);
    let gif = tmp.path().join("episode.gif");
    let e = fails(&["render", "--run", s(&run), "--task", "34", "--out", s(&gif)]);
    assert!(
        e.contains("an MT-BC-Finetune run adapts to each test task before it acts")
            && e.contains("`promptdt render` takes prompt-dt, prompt-mt-bc, mt-orl runs")
            && e.contains("`promptdt eval`"),
        "{e}"
    );
    assert!(!gif.exists(), "nothing written");
    let e = fails(&["serve", "--run", s(&run), "--listen", "127.0.0.1:0"]);
    assert!(
        e.contains("an MT-BC-Finetune run adapts to each test task before it acts")
            && e.contains("`promptdt serve` takes prompt-dt, prompt-mt-bc, mt-orl runs"),
        "{e}"
    );
}
