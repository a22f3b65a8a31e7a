//! The house's structure, checked from the sources, so that `make test` fails on a change that
//! breaks it:
//!
//! - no source file over [`MAX_LINES`] lines, except the few named in [`LONG_FILES`] with why;
//! - no import circle between the files of a crate: a file's `crate::`/`super::` paths (followed
//!   through the facades that re-export what they name, to the file that defines it) and its
//!   parent's uses of it by path (`child::Item`) are edges; references to its own ancestors are
//!   not (a module's parent declares it);
//! - (that no crate above `pdt-envs` dispatches on a family's name is checked by
//!   `crates/cli/tests/it/families.rs`, with every family through the front ends);
//! - `pdt-serve` does not depend on `pdt-train`, and serve and the Python package act through the
//!   same policy runtime (`pdt-policy`);
//! - no crate re-exports another workspace crate's items (`pub use pdt_...`): an item is imported
//!   from the crate that defines it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const MAX_LINES: usize = 800;

/// Files allowed over [`MAX_LINES`], each with the reason (flat tables or generated code). Only
/// what is over the limit today is named: nothing since the pickle machine's opcode table and
/// numpy callables went to their own files (`crates/data/src/pickle/machine/`).
const LONG_FILES: &[(&str, &str)] = &[];

fn repo_root() -> PathBuf {
    // crates/testkit -> the workspace root.
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    let mut entries: Vec<_> = entries.flatten().map(|e| e.path()).collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|e| e == "rs") {
            out.push(p);
        }
    }
}

fn crate_dirs(root: &Path) -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(root.join("crates"))
        .expect("crates/ is readable")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("Cargo.toml").is_file())
        .collect();
    dirs.sort();
    dirs
}

fn rel(root: &Path, p: &Path) -> String {
    p.strip_prefix(root).unwrap_or(p).display().to_string()
}

#[test]
fn no_source_file_is_over_the_line_limit() {
    let root = repo_root();
    let mut long = Vec::new();
    for dir in crate_dirs(&root) {
        let mut files = Vec::new();
        rust_files(&dir.join("src"), &mut files);
        for f in files {
            let n = std::fs::read_to_string(&f).expect("source readable").lines().count();
            let name = rel(&root, &f);
            if n > MAX_LINES && !LONG_FILES.iter().any(|(p, _)| *p == name) {
                long.push(format!("{name}: {n} lines"));
            }
        }
    }
    // The list stays honest: an entry that has come under the limit (or gone) is removed.
    for (name, _) in LONG_FILES {
        let n = std::fs::read_to_string(root.join(name)).map_or(0, |t| t.lines().count());
        if n <= MAX_LINES {
            long.push(format!(
                "{name}: {n} lines, no longer over the limit: remove it from LONG_FILES"
            ));
        }
    }
    assert!(long.is_empty(), "source files over {MAX_LINES} lines (split them, or name them in LONG_FILES with why):\n{}", long.join("\n"));
}

/// The module path of a source file of a crate (`src/lib.rs` -> [], `src/a/mod.rs` -> [a],
/// `src/a/b.rs` -> [a, b]); `None` for files that are not modules of the library (binaries).
fn module_path(src: &Path, file: &Path) -> Option<Vec<String>> {
    let r = file.strip_prefix(src).ok()?;
    let parts: Vec<String> = r.iter().map(|s| s.to_string_lossy().into_owned()).collect();
    let (last, dirs) = parts.split_last()?;
    let mut m: Vec<String> = dirs.to_vec();
    if dirs.first().is_some_and(|d| d == "bin") {
        return None;
    }
    match last.as_str() {
        "lib.rs" | "main.rs" if dirs.is_empty() => {}
        "mod.rs" => {}
        other => m.push(other.trim_end_matches(".rs").to_string()),
    }
    Some(m)
}

/// Expands `crate::{a::{b, c}, d}`-style trees that start at `text` (just after `crate::` or a
/// `super::` chain) into paths of identifiers.
fn expand(text: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut i = 0;
    tree(text, &mut i, &mut Vec::new(), &mut out);
    out
}

fn skip_ws(s: &str, i: &mut usize) {
    while s.as_bytes().get(*i).is_some_and(u8::is_ascii_whitespace) {
        *i += 1;
    }
}

fn ident(s: &str, i: &mut usize) -> String {
    let start = *i;
    while s.as_bytes().get(*i).is_some_and(|c| c.is_ascii_alphanumeric() || *c == b'_') {
        *i += 1;
    }
    s[start..*i].to_string()
}

fn tree(s: &str, i: &mut usize, prefix: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
    skip_ws(s, i);
    if s[*i..].starts_with('{') {
        *i += 1;
        loop {
            skip_ws(s, i);
            if *i >= s.len() {
                return;
            }
            if s[*i..].starts_with('}') {
                *i += 1;
                return;
            }
            tree(s, i, prefix, out);
            skip_ws(s, i);
            if s[*i..].starts_with(',') {
                *i += 1;
            } else if s[*i..].starts_with('}') {
                *i += 1;
                return;
            } else {
                return; // not a use tree after all
            }
        }
    }
    let id = ident(s, i);
    if id.is_empty() {
        out.push(prefix.clone()); // `*`
        return;
    }
    prefix.push(id);
    if s[*i..].starts_with("::") {
        *i += 2;
        tree(s, i, prefix, out);
    } else {
        out.push(prefix.clone());
        let mut j = *i;
        skip_ws(s, &mut j);
        if s[j..].starts_with("as ") {
            j += 3;
            skip_ws(s, &mut j);
            ident(s, &mut j);
            *i = j;
        }
    }
    prefix.pop();
}

/// The module files a file refers to through `crate::` and `super::` paths (`code`: its text
/// without comments), each through the facades that re-export what it names ([`Reexports`]).
fn references(
    code: &str,
    me: &[String],
    modules: &BTreeSet<Vec<String>>,
    reexported: &Reexports,
) -> BTreeSet<Vec<String>> {
    let mut found = BTreeSet::new();
    let mut resolve = |base: Vec<String>, rest: &str| {
        for tail in expand(rest) {
            let mut full = base.clone();
            full.extend(tail);
            // The longest prefix that is a module file, then on through re-exports of the name
            // after it (bounded: a facade of a facade at most a few levels deep).
            let longest = |path: &[String]| {
                let mut m = path.to_vec();
                while !m.is_empty() && !modules.contains(&m) {
                    m.pop();
                }
                m
            };
            let mut module = longest(&full);
            for _ in 0..8 {
                let Some(name) = full.get(module.len()).cloned() else { break };
                let Some(behind) = reexported.get(&(module.clone(), name)) else { break };
                // `facade::Name::rest` is `behind::Name::rest`.
                let rest = full.split_off(module.len());
                full = behind.iter().cloned().chain(rest).collect();
                module = longest(&full);
            }
            found.insert(module);
        }
    };
    for (i, _) in code.match_indices("crate::") {
        let before = code[..i].chars().next_back();
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == '$') {
            continue; // `pdt_crate::` or `$crate::`
        }
        resolve(Vec::new(), &code[i + "crate::".len()..]);
    }
    for (i, _) in code.match_indices("super::") {
        let before = code[..i].chars().next_back();
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':') {
            continue; // counted as part of the chain that starts earlier
        }
        let mut rest = &code[i..];
        let mut base = me.to_vec();
        while let Some(r) = rest.strip_prefix("super::") {
            base.pop();
            rest = r;
        }
        resolve(base, rest);
    }
    found
}

/// Source text without `//` comments and without the unit tests at the end of a file (they use
/// `super::*`: not the module's imports).
fn code_of(text: &str) -> String {
    let text = match text.find("#[cfg(test)]") {
        Some(i) => &text[..i],
        None => text,
    };
    text.lines()
        .map(|l| match l.find("//") {
            Some(i) => &l[..i],
            None => l,
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// The `pub use` (or `pub(crate) use`, ...) statements of `code`, each as the byte range of the
/// whole statement and its use tree (a statement may span lines): re-exports, not uses.
fn reexport_statements(code: &str) -> Vec<(std::ops::Range<usize>, &str)> {
    let mut out = Vec::new();
    let mut from = 0;
    while let Some(i) = code[from..].find("pub") {
        let start = from + i;
        from = start + 3;
        let line_start = code[..start].rfind('\n').map_or(0, |n| n + 1);
        if !code[line_start..start].trim().is_empty() {
            continue;
        }
        let mut rest = &code[start + 3..];
        if rest.starts_with('(') {
            let Some(close) = rest.find(')') else { continue };
            rest = &rest[close + 1..];
        }
        let Some(tree) = rest.trim_start().strip_prefix("use ") else { continue };
        let Some(end) = tree.find(';') else { continue };
        let tree_start = code.len() - tree.len();
        out.push((start..tree_start + end + 1, &tree[..end]));
        from = tree_start + end + 1;
    }
    out
}

/// The names a module file re-exports from its child modules (`pub use child::{X, Y}`), each with
/// the module file that defines it: a path through a facade (`crate::pack::SlotState`) leads to
/// the file behind it (`pack/engine.rs`), not to every child the facade declares.
type Reexports = BTreeMap<(Vec<String>, String), Vec<String>>;

fn reexports(code: &str, me: &[String], modules: &BTreeSet<Vec<String>>, out: &mut Reexports) {
    for (_, tree) in reexport_statements(code) {
        for path in expand(tree) {
            let Some(name) = path.last() else { continue };
            let mut full = me.to_vec();
            full.extend(path.iter().cloned());
            while !full.is_empty() && !modules.contains(&full) {
                full.pop();
            }
            if full.len() > me.len() {
                out.insert((me.to_vec(), name.clone()), full);
            }
        }
    }
}

/// The child module files a file uses by a relative path (`child::Item` in its code, or a private
/// `use child::...`; `pub use` re-exports are not uses): a parent that uses a child which reaches
/// back to the parent through a third file closes a circle, as the scripted-collection module
/// did while it matched on each family's policies and the families named its types.
fn child_uses(code: &str, me: &[String], modules: &BTreeSet<Vec<String>>) -> BTreeSet<Vec<String>> {
    let declared = code.lines().filter_map(|l| {
        let l = l.trim_start();
        let l = match l.strip_prefix("pub") {
            Some(rest) if rest.starts_with('(') => &rest[rest.find(')')? + 1..],
            Some(rest) => rest,
            None => l,
        };
        let name = l.trim_start().strip_prefix("mod ")?.trim().strip_suffix(';')?.trim();
        let mut child = me.to_vec();
        child.push(name.to_string());
        modules.contains(&child).then(|| (name.to_string(), child))
    });
    let mut uses = code.to_string();
    for (range, _) in reexport_statements(code).into_iter().rev() {
        uses.replace_range(range, "");
    }
    let mut found = BTreeSet::new();
    for (name, child) in declared {
        let needle = format!("{name}::");
        let used = uses.match_indices(&needle).any(|(i, _)| {
            let before = uses[..i].chars().next_back();
            !before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':')
        });
        if used {
            found.insert(child);
        }
    }
    found
}

#[test]
fn no_import_circle_between_files() {
    let root = repo_root();
    let mut circles = Vec::new();
    for dir in crate_dirs(&root) {
        let src = dir.join("src");
        let mut files = Vec::new();
        rust_files(&src, &mut files);
        let mut by_module: BTreeMap<Vec<String>, PathBuf> = BTreeMap::new();
        for f in &files {
            if let Some(m) = module_path(&src, f) {
                by_module.insert(m, f.clone());
            }
        }
        let modules: BTreeSet<Vec<String>> = by_module.keys().cloned().collect();
        let code: BTreeMap<&Vec<String>, String> = by_module
            .iter()
            .map(|(m, f)| (m, code_of(&std::fs::read_to_string(f).expect("source readable"))))
            .collect();
        let mut reexported = Reexports::new();
        for (m, c) in &code {
            reexports(c, m, &modules, &mut reexported);
        }
        let mut edges: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = BTreeMap::new();
        for (m, c) in &code {
            let targets = references(c, m, &modules, &reexported)
                .into_iter()
                .chain(child_uses(c, m, &modules))
                // An ancestor (or the file itself) is not an import edge: it declares this module.
                .filter(|t| !m.starts_with(t))
                .collect();
            edges.insert((*m).clone(), targets);
        }
        // Every cycle shows up as a pair a -> ... -> b -> ... -> a; report each strongly connected
        // pair of files once.
        let reach = |from: &Vec<String>| {
            let mut seen = BTreeSet::new();
            let mut stack = vec![from.clone()];
            while let Some(n) = stack.pop() {
                for t in edges.get(&n).into_iter().flatten() {
                    if seen.insert(t.clone()) {
                        stack.push(t.clone());
                    }
                }
            }
            seen
        };
        for (a, targets) in &edges {
            for b in targets {
                if a < b && reach(b).contains(a) {
                    circles.push(format!(
                        "{} <-> {}",
                        rel(&root, &by_module[a]),
                        rel(&root, &by_module[b])
                    ));
                }
            }
        }
    }
    assert!(circles.is_empty(), "import circles between files:\n{}", circles.join("\n"));
}

#[test]
fn the_module_path_parser_sees_grouped_imports() {
    let modules: BTreeSet<Vec<String>> = [
        vec![],
        vec!["a".to_string()],
        vec!["a".to_string(), "b".to_string()],
        vec!["c".to_string()],
    ]
    .into_iter()
    .collect();
    let found = references(
        "use crate::{a::b::{X, Y}, c::Z};\nfn f() { super::super::c::g() }",
        &["a".into(), "b".into()],
        &modules,
        &Reexports::new(),
    );
    let want: BTreeSet<Vec<String>> =
        [vec!["a".to_string(), "b".to_string()], vec!["c".to_string()]].into_iter().collect();
    assert_eq!(found, want);
}

/// Workspace packages a package depends on (normal dependencies, transitively).
fn transitive_deps(root: &Path, package: &str) -> BTreeSet<String> {
    let mut manifests: BTreeMap<String, toml::Table> = BTreeMap::new();
    for dir in crate_dirs(root) {
        let text = std::fs::read_to_string(dir.join("Cargo.toml")).expect("Cargo.toml");
        let t: toml::Table = text.parse().expect("Cargo.toml parses");
        let name = t["package"]["name"].as_str().expect("package.name").to_string();
        manifests.insert(name, t);
    }
    let deps_of = |p: &str| -> Vec<String> {
        manifests
            .get(p)
            .and_then(|t| t.get("dependencies"))
            .and_then(|d| d.as_table())
            .map(|d| d.keys().filter(|k| manifests.contains_key(*k)).cloned().collect())
            .unwrap_or_default()
    };
    let mut seen = BTreeSet::new();
    let mut stack = deps_of(package);
    while let Some(d) = stack.pop() {
        if seen.insert(d.clone()) {
            stack.extend(deps_of(&d));
        }
    }
    seen
}

#[test]
fn serve_and_python_act_through_one_policy_runtime_without_the_trainer() {
    let root = repo_root();
    let serve = transitive_deps(&root, "pdt-serve");
    assert!(!serve.contains("pdt-train"), "pdt-serve depends on pdt-train: {serve:?}");
    assert!(serve.contains("pdt-policy"), "pdt-serve does not use pdt-policy: {serve:?}");
    let python = transitive_deps(&root, "promptdt-python");
    assert!(
        python.contains("pdt-policy"),
        "the Python package does not use pdt-policy: {python:?}"
    );
}

#[test]
fn facades_lead_to_the_file_behind_and_parents_use_children_by_path() {
    let path = |parts: &[&str]| parts.iter().map(|s| s.to_string()).collect::<Vec<String>>();
    let modules: BTreeSet<Vec<String>> =
        [path(&[]), path(&["p"]), path(&["p", "e"]), path(&["p", "r"]), path(&["m"])]
            .into_iter()
            .collect();
    let facade =
        "mod e;\nmod r;\npub use e::{\n    S,\n    T,\n};\npub(crate) use r::run;\nfn f() { r::go() }";
    let mut reexported = Reexports::new();
    reexports(facade, &path(&["p"]), &modules, &mut reexported);
    assert_eq!(reexported.get(&(path(&["p"]), "T".into())), Some(&path(&["p", "e"])));
    assert_eq!(reexported.get(&(path(&["p"]), "run".into())), Some(&path(&["p", "r"])));
    // `crate::p::S` is `p/e.rs`'s, not every file `p` declares.
    let found = references("use crate::p::S;", &path(&["m"]), &modules, &reexported);
    assert_eq!(found, [path(&["p", "e"])].into_iter().collect());
    // `p` uses `r` (`r::go()`); it only re-exports from `e`.
    let used = child_uses(facade, &path(&["p"]), &modules);
    assert_eq!(used, [path(&["p", "r"])].into_iter().collect());
}

/// The `pub use` statements of `code` that re-export another workspace crate's items
/// (`pub use pdt_rundir::config::*`), each as its use tree on one line.
fn workspace_reexports(code: &str) -> Vec<String> {
    reexport_statements(code)
        .into_iter()
        .map(|(_, tree)| tree.split_whitespace().collect::<Vec<_>>().join(" "))
        .filter(|tree| tree.trim_start_matches("::").starts_with("pdt_"))
        .collect()
}

/// An item has one path, its owner's. A crate that re-exports another crate's items gives them a
/// second name that importers pick at random, so a crate's name stops saying what is inside it and
/// moving the item breaks whoever picked the copy; import from the crate that defines it instead.
#[test]
fn no_crate_re_exports_another_workspace_crates_items() {
    let sample = "pub use crate::a::B;\npub(crate) use pdt_x::{\n    Y,\n    Z,\n};\nuse pdt_w::V;";
    assert_eq!(workspace_reexports(sample), ["pdt_x::{ Y, Z, }"]);
    let root = repo_root();
    let mut found = Vec::new();
    for dir in crate_dirs(&root) {
        let mut files = Vec::new();
        rust_files(&dir.join("src"), &mut files);
        for f in files {
            let text = std::fs::read_to_string(&f).expect("a source file is readable");
            for tree in workspace_reexports(&code_of(&text)) {
                found.push(format!("{}: pub use {tree}", rel(&root, &f)));
            }
        }
    }
    assert!(found.is_empty(), "re-exports of another crate's items:\n{}", found.join("\n"));
}
