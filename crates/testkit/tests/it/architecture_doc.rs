//! docs/architecture.md stays true to the workspace: every crate package in the workspace
//! `Cargo.toml`'s `members` has a line in its edge list, an unmarked line lists exactly that crate's
//! workspace `[dependencies]`, and the libtorch line lists exactly the crates that depend on `tch`.
//!
//! A line marked `[redesign]` describes a crate as a restructuring in progress will leave it, so
//! only its presence is checked; the doc says to remove the mark once the change has landed.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const DOC: &str = "docs/architecture.md";
const REDESIGN: &str = "[redesign]";

/// One workspace member, as its `Cargo.toml` declares it.
#[derive(Debug)]
struct Member {
    package: String,
    /// Workspace packages among its `[dependencies]` (dev-dependencies excluded).
    workspace_deps: BTreeSet<String>,
    uses_tch: bool,
}

/// One `name -> deps` line of the doc's edge list.
#[derive(Debug)]
struct EdgeLine {
    deps: BTreeSet<String>,
    redesign: bool,
}

/// What the doc states: its edge lines by crate, and the crates on its libtorch line.
#[derive(Debug)]
struct Doc {
    edges: BTreeMap<String, EdgeLine>,
    /// `None` when the doc has no `libtorch ... <- ...` line.
    libtorch: Option<BTreeSet<String>>,
}

fn repo_root() -> PathBuf {
    // crates/testkit -> the workspace root.
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn read_toml(path: &Path) -> toml::Table {
    let text =
        std::fs::read_to_string(path).unwrap_or_else(|e| panic!("read {}: {e}", path.display()));
    text.parse::<toml::Table>().unwrap_or_else(|e| panic!("parse {}: {e}", path.display()))
}

/// The workspace members, read from the root `Cargo.toml` and each member's own.
fn workspace_members(root: &Path) -> Vec<Member> {
    let workspace = read_toml(&root.join("Cargo.toml"));
    let paths: Vec<String> = workspace["workspace"]["members"]
        .as_array()
        .expect("workspace.members is an array")
        .iter()
        .map(|m| m.as_str().expect("a member is a path").to_string())
        .collect();
    assert!(!paths.is_empty(), "workspace.members is empty");
    // First every package name, so that dependencies can be told apart from registry crates.
    let manifests: Vec<(String, toml::Table)> = paths
        .iter()
        .map(|p| {
            let manifest = read_toml(&root.join(p).join("Cargo.toml"));
            let name = manifest["package"]["name"].as_str().expect("package.name").to_string();
            (name, manifest)
        })
        .collect();
    let packages: BTreeSet<&str> = manifests.iter().map(|(n, _)| n.as_str()).collect();
    manifests
        .iter()
        .map(|(name, manifest)| {
            let deps = manifest.get("dependencies").and_then(|d| d.as_table());
            // A renamed dependency (`alias = { package = "real" }`) counts under its package name.
            let dep_packages: BTreeSet<String> = deps
                .into_iter()
                .flatten()
                .map(|(key, value)| {
                    value.get("package").and_then(|p| p.as_str()).unwrap_or(key).to_string()
                })
                .collect();
            Member {
                package: name.clone(),
                uses_tch: dep_packages.contains("tch"),
                workspace_deps: dep_packages
                    .into_iter()
                    .filter(|d| packages.contains(d.as_str()))
                    .collect(),
            }
        })
        .collect()
}

fn name_list(text: &str) -> BTreeSet<String> {
    let text = text.trim();
    if text == "(none)" {
        return BTreeSet::new();
    }
    text.split(',').map(|n| n.trim().to_string()).filter(|n| !n.is_empty()).collect()
}

/// Reads the edge and libtorch lines from the doc's fenced blocks.
fn parse_doc(text: &str) -> Doc {
    let mut edges = BTreeMap::new();
    let mut libtorch = None;
    let mut in_fence = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_fence = !in_fence;
            continue;
        }
        if !in_fence {
            continue;
        }
        if let Some((lhs, rhs)) = line.split_once(" -> ") {
            let rhs = rhs.trim();
            let (rhs, redesign) = match rhs.strip_suffix(REDESIGN) {
                Some(rest) => (rest, true),
                None => (rhs, false),
            };
            let line = EdgeLine { deps: name_list(rhs), redesign };
            let name = lhs.trim().to_string();
            assert!(edges.insert(name.clone(), line).is_none(), "{DOC}: two lines for {name}");
        } else if let Some((lhs, rhs)) = line.split_once(" <- ") {
            if lhs.trim().starts_with("libtorch") {
                libtorch = Some(name_list(rhs));
            }
        }
    }
    Doc { edges, libtorch }
}

fn names(set: &BTreeSet<String>) -> String {
    set.iter().cloned().collect::<Vec<_>>().join(", ")
}

/// Every way the doc disagrees with the workspace, each naming the crate (empty: the doc is true).
fn check(doc: &Doc, members: &[Member]) -> Vec<String> {
    let mut problems = Vec::new();
    for m in members {
        let Some(line) = doc.edges.get(&m.package) else {
            problems.push(format!("{}: workspace member missing from the edge list", m.package));
            continue;
        };
        if line.redesign {
            continue;
        }
        let missing: BTreeSet<String> = m.workspace_deps.difference(&line.deps).cloned().collect();
        let extra: BTreeSet<String> = line.deps.difference(&m.workspace_deps).cloned().collect();
        if !missing.is_empty() {
            problems.push(format!(
                "{}: edges missing from the doc: {}",
                m.package,
                names(&missing)
            ));
        }
        if !extra.is_empty() {
            problems.push(format!("{}: edges not in its Cargo.toml: {}", m.package, names(&extra)));
        }
    }
    let packages: BTreeSet<&str> = members.iter().map(|m| m.package.as_str()).collect();
    for (name, line) in &doc.edges {
        if !packages.contains(name.as_str()) && !line.redesign {
            problems.push(format!("{name}: in the edge list but not a workspace member"));
        }
    }
    match &doc.libtorch {
        None => problems.push("no `libtorch (tch) <- ...` line".to_string()),
        Some(listed) => {
            // A crate still to come (a `[redesign]` line, not yet a member) may be listed ahead.
            let ahead = |n: &String| {
                !packages.contains(n.as_str()) && doc.edges.get(n).is_some_and(|l| l.redesign)
            };
            let actual: BTreeSet<String> =
                members.iter().filter(|m| m.uses_tch).map(|m| m.package.clone()).collect();
            let missing: BTreeSet<String> = actual.difference(listed).cloned().collect();
            let extra: BTreeSet<String> =
                listed.difference(&actual).filter(|n| !ahead(n)).cloned().collect();
            if !missing.is_empty() {
                problems.push(format!("libtorch line lacks crates using tch: {}", names(&missing)));
            }
            if !extra.is_empty() {
                problems.push(format!("libtorch line names crates without tch: {}", names(&extra)));
            }
        }
    }
    problems
}

fn real_doc() -> String {
    let path = repo_root().join(DOC);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("read {}: {e}", path.display()))
}

#[test]
fn architecture_doc_matches_the_workspace() {
    let members = workspace_members(&repo_root());
    let problems = check(&parse_doc(&real_doc()), &members);
    assert!(problems.is_empty(), "{DOC} is out of date:\n  {}", problems.join("\n  "));
}

/// The check above can fail: a doc without a member's line, with a wrong edge or with a wrong
/// libtorch line is caught, and each problem names its crate.
#[test]
fn the_check_names_what_the_doc_gets_wrong() {
    let members = workspace_members(&repo_root());
    let base = members.iter().find(|m| m.package == "pdt-base").expect("pdt-base is a member");
    assert!(base.workspace_deps.is_empty() && !base.uses_tch);
    let data = members.iter().find(|m| m.package == "pdt-data").expect("pdt-data is a member");
    assert!(data.workspace_deps.contains("pdt-base"));

    let doc = real_doc();
    let broken: String = doc
        .lines()
        .filter(|l| !l.starts_with("pdt-base "))
        .map(|l| {
            if l.starts_with("pdt-data ") {
                "pdt-data -> pdt-base, pdt-model".to_string()
            } else if l.starts_with("libtorch") {
                l.replace("pdt-model", "pdt-prompt")
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    let problems = check(&parse_doc(&broken), &members);
    let has = |needle: &str| problems.iter().any(|p| p.contains(needle));
    assert!(has("pdt-base: workspace member missing"), "{problems:#?}");
    assert!(has("pdt-data: edges not in its Cargo.toml: pdt-model"), "{problems:#?}");
    assert!(has("libtorch line lacks crates using tch: pdt-model"), "{problems:#?}");
    assert!(has("libtorch line names crates without tch: pdt-prompt"), "{problems:#?}");
    assert_eq!(problems.len(), 4, "{problems:#?}");
}
