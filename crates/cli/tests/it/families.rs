//! Every family in `pdt_envs::FAMILY_NAMES` works through the front ends without being named
//! there (`docs/adding-a-family.md`): collection and replay through the real binary, and no
//! family dispatch by name in the front ends' sources.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use std::path::{Path, PathBuf};

use cli::{fails, ok, repo};
use pdt_envs::{EnvFamily, FAMILY_NAMES};

/// Writes `v` as JSON to `dir/name`; returns the path.
fn write_json(dir: &Path, name: &str, v: &serde_json::Value) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, v.to_string()).unwrap();
    p
}

/// A few actions of `family`'s task 0 to replay, and the `--init` file it needs, if any. Scripted
/// families: the first actions of an episode collected through the CLI (`data`). Others: the
/// committed MuJoCo parity fixture's first case (`testdata/mujoco/replay-<family>.json`).
fn replay_inputs(
    family: &dyn EnvFamily,
    data: &Path,
    tmp: &Path,
) -> (usize, Vec<Vec<f32>>, Option<PathBuf>) {
    let name = family.name();
    let act_dim = family.preset().act_dim;
    if family.scripted().is_some() {
        let card = pdt_data::native::read_card(data).unwrap().expect("a dataset card");
        let task = card.tasks[0].index;
        let file = data.join(&card.tasks[0].files[0].name);
        let ds = pdt_data::native::read_task_dataset(&file).unwrap();
        let t = &ds.trajectories[0];
        let actions = t.actions.chunks(act_dim).take(5).map(<[f32]>::to_vec).collect();
        return (task, actions, None);
    }
    let fixture = repo(&format!("testdata/mujoco/replay-{name}.json"));
    let text = std::fs::read_to_string(&fixture).unwrap_or_else(|e| {
        panic!("{name} takes an initial state: add {} ({e})", fixture.display())
    });
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let case = &v["cases"][0];
    let init = serde_json::json!({ "qpos": case["init_qpos"], "qvel": case["init_qvel"] });
    let actions: Vec<Vec<f32>> = serde_json::from_value(case["actions"].clone()).unwrap();
    let task = case["task"].as_u64().map_or(0, |t| t as usize);
    (task, actions.into_iter().take(5).collect(), Some(write_json(tmp, "init.json", &init)))
}

#[test]
fn every_family_collects_and_replays_through_the_cli() {
    let tmp = tempfile::tempdir().unwrap();
    for name in FAMILY_NAMES {
        let family = pdt_envs::family(name).unwrap();
        let dir = tmp.path().join(name);
        std::fs::create_dir_all(&dir).unwrap();
        let data = dir.join("data");
        let d = data.to_str().unwrap();
        match family.scripted() {
            // A scripted family: one expert episode of its first default task.
            Some(s) => {
                let task = s.default_tasks()[0].to_string();
                let shown = ok(&[
                    "collect",
                    "--env",
                    name,
                    "--tasks",
                    &task,
                    "--modes",
                    "expert",
                    "--episodes",
                    "1",
                    "--prompt-episodes",
                    "1",
                    "--out",
                    d,
                ]);
                assert!(shown.contains("wrote 2 datasets"), "{name}: {shown}");
                assert!(data.join("dataset.json").is_file(), "{name}");
            }
            // Collected from an RL agent: the CLI takes the agent's path (an empty directory
            // here, so it names the missing agent file; `collect_rl.rs` collects from the
            // committed agents), and refuses the scripted-only flags.
            None => {
                let e = fails(&[
                    "collect",
                    "--env",
                    name,
                    "--from-pretrained",
                    "--pretrained-dir",
                    dir.to_str().unwrap(),
                    "--out",
                    d,
                ]);
                assert!(e.contains("agent.json"), "{name}: {e}");
                let e = fails(&["collect", "--env", name, "--modes", "expert", "--out", d]);
                assert!(e.contains("--modes is for the scripted families"), "{name}: {e}");
                assert!(family.rl_preset().is_some(), "{name}: no configs/collect/{name}.toml");
            }
        }
        let (task, actions, init) = replay_inputs(family.as_ref(), &data, &dir);
        let acts = write_json(&dir, "actions.json", &serde_json::json!(actions));
        let out = dir.join("replay.json");
        let task = task.to_string();
        let mut args = vec!["env", "replay", "--env", name, "--task", &task];
        args.extend(["--actions", acts.to_str().unwrap(), "--out", out.to_str().unwrap()]);
        if let Some(i) = &init {
            args.extend(["--init", i.to_str().unwrap()]);
        }
        let shown = ok(&args);
        assert!(shown.contains(&format!("{name} task {task}: ")), "{name}: {shown}");
        let r: pdt_envs::ReplayResult =
            serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
        assert_eq!((r.family.as_str(), r.rewards.len()), (name, actions.len()), "{name}");
        // The success flags are there exactly for the families with a success rule.
        assert_eq!(r.success.len(), family.success_reward().map_or(0, |_| actions.len()), "{name}");
    }
}

/// Quoted family names in the code of `text`: outside comments, Python docstrings (`py`) and
/// `#[cfg(test)]` modules (a test module is the last item of a file in this workspace).
fn quoted_family_names(text: &str, py: bool) -> Vec<(usize, &'static str)> {
    let mut found = Vec::new();
    let mut in_docstring = false;
    for (i, line) in text.lines().enumerate() {
        if line.trim_start().starts_with("#[cfg(test)]") {
            break;
        }
        if py && line.contains("\"\"\"") {
            // A docstring line: it opens or closes one unless it does both.
            in_docstring ^= line.matches("\"\"\"").count() % 2 == 1;
            continue;
        }
        if in_docstring {
            continue;
        }
        let code = line.split(if py { "#" } else { "//" }).next().unwrap_or("");
        for name in FAMILY_NAMES {
            if code.contains(&format!("\"{name}\"")) || code.contains(&format!("'{name}'")) {
                found.push((i + 1, name));
            }
        }
    }
    found
}

fn files_under(dir: &Path, ext: &str, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let p = entry.unwrap().path();
        if p.is_dir() {
            files_under(&p, ext, out);
        } else if p.extension().is_some_and(|e| e == ext) {
            out.push(p);
        }
    }
}

/// The front ends take every family from pdt-envs: no family name as a string in their code
/// (help text is in doc comments; the experiment manifests' parser and its tests are exempt, as
/// manifests name the families of the paper's figures).
#[test]
fn front_ends_name_no_family() {
    let mut files = Vec::new();
    for krate in [
        // Not `rundir`: its configuration's default `env.name` is a value, as a manifest's.
        "cli", "python", "repro", "report", "rl", "bench", "train", "eval", "policy", "serve",
    ] {
        files_under(&repo(&format!("crates/{krate}/src")), "rs", &mut files);
    }
    files_under(&repo("crates/python/python/promptdt"), "py", &mut files);
    assert!(files.len() > 20, "{} files: wrong directory?", files.len());
    let exempt = [repo("crates/repro/src/manifest.rs")];
    let mut named = Vec::new();
    for f in files.iter().filter(|f| !exempt.contains(f)) {
        let text = std::fs::read_to_string(f).unwrap();
        let py = f.extension().is_some_and(|e| e == "py");
        for (line, name) in quoted_family_names(&text, py) {
            named.push(format!("{}:{line}: {name}", f.display()));
        }
    }
    assert!(named.is_empty(), "family dispatch by name in the front ends:\n{}", named.join("\n"));
}
