//! `make test`, `make demo` and the wheel share one build of the library crates, so
//! none of them builds libtorch's crates twice.
//!
//! Cargo turns on a dependency's features for the packages one command selects, and builds a
//! dependency again (with every crate above it) for each different feature set. `make test` selects
//! the whole workspace with its dev-dependencies, `make demo` only the `promptdt` package and
//! maturin only `promptdt-python`. The two narrow selections therefore list, in their Cargo.toml
//! ("One build" sections), the dependencies whose features the rest of the workspace turns on. This
//! test asks `cargo tree` for the three resolutions and checks that every package the narrow builds
//! share with `make test`'s is resolved with the same features, and names each difference.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

fn repo_root() -> PathBuf {
    // crates/testkit -> the workspace root.
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// `package version` -> the feature sets it is built with in one selection (a package built for
/// the host and for the target can have two).
fn resolve(args: &[&str]) -> BTreeMap<String, BTreeSet<String>> {
    // `cargo test` runs the tests with CARGO set to the cargo that runs them.
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".to_string());
    let out = Command::new(&cargo)
        .current_dir(repo_root())
        .args(["tree", "--offline", "--prefix", "none", "--format", "{p} [{f}]"])
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("run {cargo} tree: {e}"));
    assert!(
        out.status.success(),
        "cargo tree {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut packages: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        // `name vX.Y.Z (/path)? (proc-macro)? [features] (*)?`
        let Some((head, rest)) = line.split_once(" [") else { continue };
        let Some((features, _)) = rest.split_once(']') else { continue };
        let mut words = head.split_whitespace();
        let (Some(name), Some(version)) = (words.next(), words.next()) else { continue };
        packages.entry(format!("{name} {version}")).or_default().insert(features.to_string());
    }
    assert!(packages.len() > 50, "cargo tree {args:?} listed only {} packages", packages.len());
    packages
}

/// Each package of `narrow` whose feature sets are not all among `wide`'s, with both.
fn differences(
    narrow: &BTreeMap<String, BTreeSet<String>>,
    wide: &BTreeMap<String, BTreeSet<String>>,
) -> Vec<String> {
    narrow
        .iter()
        .filter_map(|(package, sets)| {
            let theirs = wide.get(package)?;
            (!sets.is_subset(theirs))
                .then(|| format!("{package}: {sets:?} here, {theirs:?} in `make test`"))
        })
        .collect()
}

#[test]
fn demo_and_wheel_resolve_the_features_make_test_resolves() {
    let test = resolve(&["--workspace", "--edges", "normal,build,dev"]);
    for (package, command) in
        [("promptdt", "make demo"), ("promptdt-python", "the wheel (maturin)")]
    {
        let narrow = resolve(&["--package", package, "--edges", "normal,build"]);
        assert!(
            narrow.keys().any(|p| p.starts_with("pdt-base ")),
            "{package} does not build pdt-base"
        );
        let diff = differences(&narrow, &test);
        assert!(
            diff.is_empty(),
            "{command} (`-p {package}`) would build these dependencies with other features than `make \
             test`, and so every library crate above them again; add the missing features to the \
             \"One build\" section of {package}'s Cargo.toml:\n  {}",
            diff.join("\n  ")
        );
    }
}

#[test]
fn a_feature_difference_is_reported() {
    let one = |features: &str| BTreeSet::from([features.to_string()]);
    let wide = BTreeMap::from([("serde_json v1".to_string(), one("default,raw_value,std"))]);
    let same = BTreeMap::from([("serde_json v1".to_string(), one("default,raw_value,std"))]);
    let fewer = BTreeMap::from([("serde_json v1".to_string(), one("default,std"))]);
    let absent = BTreeMap::from([("memchr v2".to_string(), one("std"))]);
    assert!(differences(&same, &wide).is_empty());
    assert!(
        differences(&absent, &wide).is_empty(),
        "a package only the narrow build has is not shared"
    );
    assert_eq!(differences(&fewer, &wide).len(), 1);
}
