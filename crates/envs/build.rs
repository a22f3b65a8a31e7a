//! Makes the MuJoCo 3.17.0 shared library available to pdt-envs and everything that depends on it,
//! with no exports (see `docs/mujoco-envs.md`, "Set-up").
//!
//! mujoco-rs's own build script finds the library through pkg-config (`.cargo/config.toml` sets
//! `PKG_CONFIG_PATH` to the committed `pkgconfig/`, whose `mujoco.pc` points at
//! `third_party/mujoco`) and emits `-lmujoco`; pkg-config does not check that the file exists and
//! mujoco-rs sets no rpath. This script, which Cargo runs before any binary of the workspace that
//! links pdt-envs is linked:
//! 1. runs `scripts/fetch_mujoco.py` when `third_party/mujoco` is not installed yet;
//! 2. symlinks the library into `OUT_DIR` and adds `OUT_DIR` as a native link-search path: Cargo
//!    puts such paths (inside the target dir) on the library path of `cargo run` / `cargo test`
//!    for every crate that depends on pdt-envs;
//! 3. adds an rpath to pdt-envs's own test, bench and example binaries, so they also run straight
//!    from `target/` without `LD_LIBRARY_PATH`;
//! 4. runs `scripts/fetch_metaworld.py` when `third_party/metaworld` (Meta-World 3.1.1's reach
//!    scene, which `src/metaworld_reach.rs` embeds with `include_bytes!`) is not installed yet.

use std::path::{Path, PathBuf};
use std::process::Command;

const MUJOCO_VERSION: &str = "3.17.0";
const LIB_NAME: &str = "libmujoco.so.3.17.0";
const METAWORLD_VERSION: &str = "3.1.1";

fn main() {
    let manifest_dir = PathBuf::from(env("CARGO_MANIFEST_DIR"));
    let root = manifest_dir.join("..").join("..");
    let root = root.canonicalize().unwrap_or(root);
    let install = root.join("third_party").join("mujoco");
    let stamp = install.join("build-version");
    let script = root.join("scripts").join("fetch_mujoco.py");
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rerun-if-changed={}", script.display());
    println!("cargo::rerun-if-changed={}", stamp.display());
    println!("cargo::rerun-if-env-changed=PYTHON");
    let mw_stamp = root.join("third_party").join("metaworld").join("build-version");
    let mw_script = root.join("scripts").join("fetch_metaworld.py");
    println!("cargo::rerun-if-changed={}", mw_script.display());
    println!("cargo::rerun-if-changed={}", mw_stamp.display());

    if std::env::var("DOCS_RS").is_ok() {
        return; // docs.rs builds without linking
    }

    let installed = std::fs::read_to_string(&stamp).map(|s| s.trim() == MUJOCO_VERSION);
    if !matches!(installed, Ok(true)) {
        fetch(&script, &format!("MuJoCo {MUJOCO_VERSION} not found in third_party/mujoco"));
    }
    // (4) Before compiling: the crate include_bytes!'s these files.
    let mw_installed = std::fs::read_to_string(&mw_stamp).map(|s| s.trim() == METAWORLD_VERSION);
    if !matches!(mw_installed, Ok(true)) {
        fetch(
            &mw_script,
            &format!(
                "the Meta-World {METAWORLD_VERSION} reach scene is not in third_party/metaworld"
            ),
        );
    }
    let lib_dir = install.join("lib");
    let lib = lib_dir.join(LIB_NAME);
    if !lib.is_file() {
        fail(&format!(
            "{} is missing after running {}; run it by hand to see why",
            lib.display(),
            script.display()
        ));
    }

    // (2) OUT_DIR lies inside the target dir, which is what Cargo adds to the run-time library path.
    let out_dir = PathBuf::from(env("OUT_DIR"));
    for name in [LIB_NAME, "libmujoco.so"] {
        let link = out_dir.join(name);
        let _ = std::fs::remove_file(&link); // a stale link from an earlier build
        if let Err(e) = std::os::unix::fs::symlink(&lib, &link) {
            fail(&format!("cannot symlink {} to {}: {e}", link.display(), lib.display()));
        }
    }
    println!("cargo::rustc-link-search=native={}", out_dir.display());
    // (3) Only affects this package's linked targets (tests, benches, examples).
    println!("cargo::rustc-link-arg=-Wl,-rpath,{}", lib_dir.display());
}

fn fetch(script: &Path, why: &str) {
    let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".to_string());
    println!("cargo::warning={why}: running {}", script.display());
    let status = Command::new(&python).arg(script).status();
    match status {
        Ok(s) if s.success() => {}
        Ok(s) => fail(&format!("{python} {} failed ({s})", script.display())),
        Err(e) => fail(&format!(
            "cannot run {python} {} ({e}); set PYTHON to a Python 3",
            script.display()
        )),
    }
}

fn env(name: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| fail(&format!("Cargo did not set {name}")))
}

fn fail(message: &str) -> ! {
    eprintln!("pdt-envs build script: {message}");
    std::process::exit(1);
}
