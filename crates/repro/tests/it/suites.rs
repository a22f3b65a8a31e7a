//! A user's experiment manifest naming task suites (`[suites.<name>]`): its paths taken from the
//! manifest file's directory, its cells planned on the suite file and the user's data, its data
//! checked (never collected), and what is wrong named.

use pdt_repro::exec::ensure_data;
use pdt_repro::{ExecOptions, Manifest, PlanOptions};
use std::path::Path;

const SUITE: &str = r#"
name = "tiny"
obs_dim = 3
act_dim = 1
action_bound = 2.0
max_ep_len = 20
rtg_scale = 10
target_return = -5.0
prompt_length = 5

[[tasks]]
name = "a"
params = { g = 1.0 }

[[tasks]]
name = "b"
params = { g = 2.0 }

[[tasks]]
name = "c"
params = { g = 3.0 }

[splits.default]
train = ["a", "b"]
test = ["c"]
"#;

const MANIFEST: &str = r#"
name = "mine"
title = "t"
description = "d"
layout = "curves"

[suites.tiny_suite]
file = "suites/tiny.toml"
data = "data/tiny"
collect = "python collect.py"

[[claims]]
text = "Prompt-DT beats MT-ORL"
kind = "better"
a = "tiny_suite/prompt-dt"
b = "tiny_suite/mt-orl"

[budgets.smoke]
note = "n"
iterations = 2
seeds = 1
learning_rate = 1e-3
warmup_steps = 50

[[budgets.smoke.rules]]
envs = ["tiny_suite"]
iterations = 3

[[cells]]
env = "tiny_suite"
method = "prompt-dt"

[[cells]]
env = "tiny_suite"
method = "mt-orl"
"#;

/// A manifest file `exp/manifest.toml` with `text`, and the suite file beside it.
fn tree(text: &str) -> (tempfile::TempDir, String) {
    let d = tempfile::tempdir().expect("tempdir");
    std::fs::create_dir_all(d.path().join("exp/suites")).expect("mkdir");
    std::fs::write(d.path().join("exp/suites/tiny.toml"), SUITE).expect("suite");
    let manifest = d.path().join("exp/manifest.toml");
    std::fs::write(&manifest, text).expect("manifest");
    let path = manifest.to_string_lossy().into_owned();
    (d, path)
}

fn options(out: &Path) -> PlanOptions {
    PlanOptions {
        budget: "smoke".into(),
        out: out.to_path_buf(),
        data_root: out.join("data"),
        threads: 1,
        device: Default::default(),
        matmul: Default::default(),
        seeds: None,
    }
}

#[test]
fn a_manifest_file_plans_its_cells_on_its_suites_and_their_data() {
    let (d, path) = tree(MANIFEST);
    let m = Manifest::load(&path).expect("loads");
    let exp = d.path().join("exp");
    let suite = exp.join("suites/tiny.toml");
    // Taken from the manifest's directory, not the working directory.
    assert_eq!(m.family_name("tiny_suite"), suite.to_string_lossy());
    assert_eq!(m.family_name("cheetah_dir"), "cheetah_dir");
    assert_eq!(m.family("tiny_suite").expect("family").split("default").expect("split").1, [2]);

    let out = d.path().join("out");
    let plan = pdt_repro::plan::plan(&m, &options(&out)).expect("plans");
    let keys: Vec<&str> = plan.runs.iter().map(|r| r.key.as_str()).collect();
    assert_eq!(keys, ["tiny_suite/prompt-dt/smoke/seed0", "tiny_suite/mt-orl/smoke/seed0"]);
    for r in &plan.runs {
        assert_eq!(r.config.env.name, suite.to_string_lossy(), "the run trains on the suite file");
        assert_eq!(r.config.data.dir, exp.join("data/tiny"), "the user's data, not <out>/data");
        assert_eq!(r.data.dir, exp.join("data/tiny"));
        assert!(r.data.prepared.is_some());
        assert_eq!(r.config.train.iterations, 3, "a rule's `envs` names the suite");
        assert_eq!((r.config.optim.learning_rate, r.config.optim.warmup_steps), (1e-3, 50));
    }
    assert_eq!(plan.data().len(), 1, "the cells share the suite's data");
}

#[test]
fn a_suites_data_are_checked_not_collected() {
    let (d, path) = tree(MANIFEST);
    let m = Manifest::load(&path).expect("loads");
    let plan = pdt_repro::plan::plan(&m, &options(&d.path().join("out"))).expect("plans");
    let data = plan.data().remove(0);
    let opts = ExecOptions {
        // Never run: a suite's data are not collected.
        exe: d.path().join("no-such-promptdt"),
        jobs: 1,
        omp_wait_policy: None,
        pretrained_root: d.path().join("no-agents"),
        pack: 1,
        pack_engine: pdt_rundir::pack::Engine::Solo,
    };
    let err = ensure_data(&data, &opts).expect_err("no data yet").to_string();
    for want in ["tiny_suite", "data/tiny", "suites.tiny_suite.data", "python collect.py"] {
        assert!(err.contains(want), "{want:?} not in: {err}");
    }
    std::fs::create_dir_all(&data.dir).expect("mkdir");
    std::fs::write(data.dir.join("tiny-0-expert.safetensors"), b"").expect("file");
    assert!(!ensure_data(&data, &opts).expect("there"), "nothing collected");
    pdt_repro::exec::check_agents(&plan, &opts.pretrained_root).expect("a suite needs no agent");
}

#[test]
fn bad_suites_are_refused_by_name() {
    for (from, to, want) in [
        // A cell naming neither a family nor a suite lists the suites.
        ("env = \"tiny_suite\"\nmethod = \"mt-orl\"", "env = \"tiny\"\nmethod = \"mt-orl\"", "unknown environment \"tiny\" (a built-in family, or a suite named in [suites]: tiny_suite)"),
        // The suite file's own error, under the manifest's key.
        ("file = \"suites/tiny.toml\"", "file = \"suites/missing.toml\"", "suites.tiny_suite"),
        ("collect = \"python collect.py\"", "colect = 1", "unknown field `colect`"),
        ("data = \"data/tiny\"\n", "", "missing field `data`"),
    ] {
        assert!(MANIFEST.contains(from), "{from}");
        let (_d, path) = tree(&MANIFEST.replacen(from, to, 1));
        let err = Manifest::load(&path).expect_err(to).to_string();
        assert!(err.contains(want), "{to}: {want:?} not in: {err}");
    }
    let missing = {
        let (_d, path) = tree(&MANIFEST.replacen("suites/tiny.toml", "suites/missing.toml", 1));
        Manifest::load(&path).expect_err("missing").to_string()
    };
    assert!(missing.contains("missing.toml"), "the missing file is named: {missing}");
    // A built-in family's name cannot name a suite: a cell naming it would be ambiguous.
    let builtin = MANIFEST
        .replace("suites.tiny_suite]", "suites.point_robot]")
        .replace("\"tiny_suite", "\"point_robot");
    let (_d, path) = tree(&builtin);
    let err = Manifest::load(&path).expect_err("built-in name").to_string();
    assert!(err.contains("suites.point_robot") && err.contains("built-in"), "{err}");
}

#[test]
fn the_metaworld_example_manifest_plans_on_its_committed_suites() {
    // Read from the checkout (its suite files are committed; its data and venv are not needed to
    // plan): docs/your-own-tasks.md's worked example stays a manifest `reproduce` accepts.
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples/metaworld_ml1/experiment.toml");
    let m = Manifest::load(&path.to_string_lossy()).expect("the example manifest loads");
    let d = tempfile::tempdir().expect("tempdir");
    let plan =
        pdt_repro::plan::plan(&m, &PlanOptions { budget: "cpu".into(), ..options(d.path()) })
            .expect("plans");
    assert_eq!(plan.runs.len(), 12, "2 suites x 2 methods x 3 seeds");
    for r in &plan.runs {
        assert!(r.config.env.name.ends_with("-v3.toml"), "{}", r.config.env.name);
        assert!(
            r.data.prepared.is_some()
                && r.data.dir.ends_with(r.config.data.dir.file_name().unwrap_or_default())
        );
    }
    for env in ["ml1_push", "ml1_pick_place"] {
        let family = m.family(env).expect("suite");
        assert_eq!((family.num_tasks(), family.split("default").expect("split").1.len()), (50, 5));
    }
}
