//! Experiment files from hostile hands: any text either fails to parse (naming line and column),
//! fails validation (naming the setting), or is a configuration that writes back to itself.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_rundir::config::TrainConfig;
use proptest::prelude::*;

/// Every setting a user can write, as (section, key).
const KEYS: &[(&str, &str)] = &[
    ("run", "seed"),
    ("run", "threads"),
    ("sampler", "k"),
    ("sampler", "prompt_episodes"),
    ("sampler", "prompt_length"),
    ("sampler", "batch_size_per_task"),
    ("sampler", "rtg_scale"),
    ("model", "hidden_size"),
    ("model", "n_layer"),
    ("model", "n_head"),
    ("model", "n_inner"),
    ("model", "max_ep_len"),
    ("model", "n_positions"),
    ("model", "dropout"),
    ("model", "embd_dropout"),
    ("optim", "learning_rate"),
    ("optim", "beta1"),
    ("optim", "beta2"),
    ("optim", "eps"),
    ("optim", "weight_decay"),
    ("optim", "warmup_steps"),
    ("optim", "grad_clip_norm"),
    ("optim", "flat"),
    ("train", "iterations"),
    ("train", "steps_per_iteration"),
    ("train", "test_eval_interval"),
    ("train", "train_eval_interval"),
    ("train", "save_interval"),
    ("train", "resume_interval"),
    ("eval", "episodes"),
    ("eval", "target_return"),
    ("eval", "max_batch"),
    ("eval", "env_threads"),
    ("eval", "finetune_steps"),
    ("eval", "finetune_batch"),
    ("eval", "finetune_lr"),
];

/// TOML values at the edges: signs, zero, huge, NaN, infinities, wrong types.
fn value() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("0".to_string()),
        Just("-1".to_string()),
        Just("1".to_string()),
        Just("9223372036854775807".to_string()),
        Just("-9223372036854775808".to_string()),
        Just("nan".to_string()),
        Just("inf".to_string()),
        Just("-inf".to_string()),
        Just("1e30".to_string()),
        Just("-0.0".to_string()),
        Just("0.5".to_string()),
        Just("2.0".to_string()),
        Just("\"text\"".to_string()),
        Just("\"on\"".to_string()),
        Just("[]".to_string()),
        Just("true".to_string()),
        any::<i64>().prop_map(|x| x.to_string()),
        any::<f64>().prop_filter("finite", |x| x.is_finite()).prop_map(|x| format!("{x:e}")),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1024))]

    #[test]
    fn any_setting_value_is_refused_by_name_or_round_trips(
        picks in prop::collection::vec((0..KEYS.len(), value()), 1..4),
    ) {
        let mut text = String::new();
        let mut sections: Vec<(&str, Vec<String>)> = Vec::new();
        for (k, v) in &picks {
            let (sec, key) = KEYS[*k];
            let line = format!("{key} = {v}");
            match sections.iter_mut().find(|(s, _)| *s == sec) {
                Some((_, lines)) if !lines.iter().any(|l| l.starts_with(&format!("{key} ="))) => {
                    lines.push(line)
                }
                Some(_) => {}
                None => sections.push((sec, vec![line])),
            }
        }
        for (sec, lines) in &sections {
            text.push_str(&format!("[{sec}]\n{}\n", lines.join("\n")));
        }
        let cfg: TrainConfig = match toml::from_str(&text) {
            Ok(c) => c,
            Err(e) => {
                // type errors name the key
                let m = e.to_string();
                prop_assert!(picks.iter().any(|(k, _)| m.contains(KEYS[*k].1)) || m.contains("line"), "{m}");
                return Ok(());
            }
        };
        match cfg.validate() {
            Err(e) => {
                let m = e.to_string();
                prop_assert!(
                    picks.iter().any(|(k, _)| m.contains(&format!("{}.{}", KEYS[*k].0, KEYS[*k].1))),
                    "{text}\n{m}"
                );
            }
            Ok(()) => {
                let back: TrainConfig = toml::from_str(&cfg.to_toml().unwrap()).unwrap();
                // NaN is not equal to itself; validation admits no NaN, so equality must hold
                prop_assert_eq!(back, cfg);
            }
        }
    }

    /// Random text never panics the reader.
    #[test]
    fn random_text_never_panics(text in "(\\[[a-z]{1,8}\\]\n)?([a-z_]{1,12} = .{0,12}\n){0,4}") {
        if let Ok(c) = toml::from_str::<TrainConfig>(&text) {
            let _ = c.validate();
        }
    }
}

/// Every experiment file shipped in `configs/` reads and validates (`configs/collect/` holds the
/// RL collection presets, another schema, read by `pdt-envs` and `pdt-rl`).
#[test]
fn every_shipped_config_validates() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
    let mut n = 0;
    for family in std::fs::read_dir(&root).unwrap() {
        let family = family.unwrap().path();
        if family.file_name().is_some_and(|n| n == "collect") {
            continue;
        }
        for f in std::fs::read_dir(family).unwrap() {
            let path = f.unwrap().path();
            if path.extension().and_then(|e| e.to_str()) != Some("toml") {
                continue;
            }
            let cfg = TrainConfig::from_file(&path).unwrap_or_else(|e| panic!("{e}"));
            cfg.validate().unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            n += 1;
        }
    }
    assert!(n >= 5, "found {n} configs");
}

/// The shipped MACAW experiment files are the Prompt-DT table's preset, written out.
#[test]
fn shipped_macaw_configs_are_the_promptdt_preset() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
    for env in ["cheetah_dir", "cheetah_vel", "ant_dir"] {
        let cfg = TrainConfig::from_file(&root.join(env).join("macaw.toml")).unwrap();
        assert_eq!(cfg.run.method, pdt_rundir::config::Method::Macaw);
        assert_eq!(
            cfg.macaw,
            pdt_rundir::config::macaw::MacawConfig::preset(
                pdt_rundir::config::macaw::Preset::Promptdt,
                5
            ),
            "{env}"
        );
    }
}
