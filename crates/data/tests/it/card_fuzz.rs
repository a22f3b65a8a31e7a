//! Dataset cards (`dataset.json`) from hostile hands: random corruption and random field values
//! never panic; a card is either refused with its path named or agrees with the files it describes.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_data::multitask::{load_multitask, DatasetSpec};
use pdt_data::native::{
    read_card, write_card, write_task_dataset, CardFile, CardTask, DatasetCard, FileMeta,
};
use pdt_data::{TaskDataset, Trajectory};
use proptest::prelude::*;
use std::path::Path;

fn dataset(seed: u32) -> TaskDataset {
    let t = 5;
    let f = |k: usize| (seed as f32 + k as f32 * 0.25).sin();
    let traj = Trajectory::new(
        2,
        2,
        (0..t * 2).map(f).collect(),
        (0..t * 2).map(f).collect(),
        (0..t).map(f).collect(),
        vec![false; t],
        (0..t).map(|k| k == t - 1).collect(),
    )
    .unwrap();
    TaskDataset::new(vec![traj]).unwrap()
}

/// A valid directory: tasks 0 and 1 of `e`, expert and prompt files, and its card.
fn valid_dir(dir: &Path) -> String {
    let mut tasks = Vec::new();
    for i in 0..2 {
        let mut files = Vec::new();
        for mode in ["expert", "prompt-expert"] {
            let name = format!("e-{i}-{mode}.safetensors");
            let ds = dataset(i);
            let meta = FileMeta {
                env: Some("e".into()),
                task_index: Some(i as usize),
                mode: Some(mode.into()),
            };
            write_task_dataset(&dir.join(&name), &ds, &meta).unwrap();
            files.push(CardFile::describe(&name, mode, &ds));
        }
        tasks.push(CardTask { index: i as usize, params: serde_json::json!({}), files });
    }
    let card = DatasetCard {
        format: "promptdt-dataset".into(),
        format_version: "1".into(),
        env: "e".into(),
        obs_dim: 2,
        act_dim: 2,
        tasks,
        generator: serde_json::Value::Null,
    };
    write_card(dir, &card).unwrap();
    std::fs::read_to_string(dir.join("dataset.json")).unwrap()
}

/// Hostile values for any JSON field.
fn value() -> impl Strategy<Value = serde_json::Value> {
    prop_oneof![
        Just(serde_json::Value::Null),
        any::<bool>().prop_map(serde_json::Value::from),
        any::<i64>().prop_map(serde_json::Value::from),
        any::<u64>().prop_map(serde_json::Value::from),
        any::<f64>().prop_map(|x| serde_json::json!(x)),
        Just(serde_json::json!("../../../etc/passwd")),
        Just(serde_json::json!("/dev/zero")),
        Just(serde_json::json!("e-0-expert.safetensors")),
        Just(serde_json::json!("cheetah_dir")),
        ".{0,12}".prop_map(serde_json::Value::from),
        Just(serde_json::json!([])),
        Just(serde_json::json!({})),
    ]
}

/// Every path to a leaf of `v` (object keys and array indices).
fn leaves(v: &serde_json::Value, at: Vec<String>, out: &mut Vec<Vec<String>>) {
    match v {
        serde_json::Value::Object(m) => m.iter().for_each(|(k, x)| {
            let mut p = at.clone();
            p.push(k.clone());
            leaves(x, p, out);
        }),
        serde_json::Value::Array(a) => a.iter().enumerate().for_each(|(i, x)| {
            let mut p = at.clone();
            p.push(i.to_string());
            leaves(x, p, out);
        }),
        _ => out.push(at),
    }
}

fn set(v: &mut serde_json::Value, path: &[String], to: serde_json::Value) {
    let mut cur = v;
    for k in path {
        cur = match cur {
            serde_json::Value::Object(m) => m.get_mut(k).unwrap(),
            serde_json::Value::Array(a) => &mut a[k.parse::<usize>().unwrap()],
            _ => unreachable!(),
        };
    }
    *cur = to;
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// One field set to a hostile value: the card is refused (naming dataset.json) or, when
    /// `train` would use it, it agrees with the files.
    #[test]
    fn hostile_field_values_are_refused_or_consistent(which in any::<prop::sample::Index>(), to in value()) {
        let dir = tempfile::tempdir().unwrap();
        let text = valid_dir(dir.path());
        let mut card: serde_json::Value = serde_json::from_str(&text).unwrap();
        let mut paths = Vec::new();
        leaves(&card, Vec::new(), &mut paths);
        let path = which.get(&paths).clone();
        set(&mut card, &path, to);
        std::fs::write(dir.path().join("dataset.json"), card.to_string()).unwrap();
        match read_card(dir.path()) {
            Err(e) => prop_assert!(e.to_string().contains("dataset.json"), "{e}"),
            Ok(c) => {
                let c = c.unwrap();
                for f in c.tasks.iter().flat_map(|t| &t.files) {
                    prop_assert!(!f.name.contains('/') && f.name != ".." , "{}", f.name);
                }
            }
        }
        match load_multitask(&DatasetSpec::new(dir.path(), "e", vec![0, 1])) {
            Ok(set) => {
                let c = read_card(dir.path()).unwrap().unwrap();
                prop_assert_eq!(c.env.as_str(), "e");
                prop_assert_eq!((c.obs_dim, c.act_dim), (set.obs_dim, set.act_dim));
            }
            Err(e) => prop_assert!(e.to_string().contains("dataset.json"), "{e}"),
        }
    }

    /// Random byte corruption and truncation of the card never panic.
    #[test]
    fn corrupted_cards_never_panic(
        edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..6),
        cut in prop::option::of(any::<prop::sample::Index>()),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let mut b = valid_dir(dir.path()).into_bytes();
        for (i, v) in edits {
            let i = i.index(b.len());
            b[i] = v;
        }
        if let Some(c) = cut {
            b.truncate(c.index(b.len()));
        }
        std::fs::write(dir.path().join("dataset.json"), &b).unwrap();
        let _ = read_card(dir.path());
        let _ = load_multitask(&DatasetSpec::new(dir.path(), "e", vec![0, 1]));
    }
}

/// Found by the property test above: `Path::components` ignores a trailing separator, so "x/"
/// looked like a plain name.
#[test]
fn a_name_with_a_trailing_separator_is_not_plain() {
    for name in ["x/", "\u{a1}/", "a\\b", "..", "/etc/passwd", "a/../b"] {
        let dir = tempfile::tempdir().unwrap();
        let quoted = serde_json::to_string(name).unwrap();
        let text = valid_dir(dir.path()).replacen("\"e-0-expert.safetensors\"", &quoted, 1);
        std::fs::write(dir.path().join("dataset.json"), text).unwrap();
        let e = read_card(dir.path()).unwrap_err().to_string();
        assert!(e.contains("not a plain file name"), "{name}: {e}");
    }
}
