//! `RESULTS.md` and the README's headline block are generated from the committed results registry
//! (`results/`), never typed: regenerated here, they must equal the committed files byte for byte
//! (after adding a run: `promptdt results render`).

use pdt_repro::render::{render, splice_readme};
use std::path::{Path, PathBuf};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn read(p: &Path) -> String {
    std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn committed_results_md_and_readme_block_are_the_generators_output() {
    let root = repo();
    let r = render(&root.join("results")).unwrap_or_else(|e| panic!("render: {e}"));
    // Every archived run shows up: an empty registry would render an empty (and matching) file.
    assert!(
        r.results_md.contains("| Prompt-DT `cheetah_vel/prompt-dt` | cpu |"),
        "{}",
        r.results_md
    );
    let committed = read(&root.join("RESULTS.md"));
    assert!(
        committed == r.results_md,
        "RESULTS.md differs from what `promptdt results render` writes from results/; run it"
    );
    let readme = read(&root.join("README.md"));
    let spliced = splice_readme(&readme, &r.readme_block).unwrap_or_else(|e| panic!("{e}"));
    assert!(
        spliced == readme,
        "README.md's results block differs from what `promptdt results render` writes; run it"
    );
}

#[test]
fn a_readme_without_the_markers_is_refused() {
    assert!(splice_readme("# no markers\n", "x\n").is_err());
    let spliced =
        splice_readme("a\n<!-- results:begin -->\nold\n<!-- results:end -->\nb\n", "new\n");
    assert_eq!(
        spliced.ok().as_deref(),
        Some("a\n<!-- results:begin -->\nnew\n<!-- results:end -->\nb\n")
    );
}

/// The text of `doc` between `begin` and `end` (the marker lines excluded).
fn block<'a>(doc: &'a str, begin: &str, end: &str) -> Option<&'a str> {
    let start = doc.find(begin)? + begin.len();
    let stop = doc[start..].find(end)? + start;
    Some(doc[start..stop].strip_prefix('\n').unwrap_or(&doc[start..stop]))
}

/// docs/reproduce.md#claims quotes the rule's worked example: computed by the code, never typed.
#[test]
fn the_docs_worked_example_of_the_claim_rule_is_the_codes_output() {
    let (begin, end) = ("<!-- claims-example:begin -->", "<!-- claims-example:end -->");
    let path = repo().join("docs/reproduce.md");
    let doc = read(&path);
    let quoted = block(&doc, begin, end)
        .unwrap_or_else(|| panic!("{}: no {begin} ... {end} block", path.display()));
    let expected = pdt_repro::stats::worked_example();
    assert!(
        quoted == expected,
        "{}: the block between {begin} and {end} differs from stats::worked_example(); replace it \
         with these lines:\n{expected}",
        path.display()
    );
}

/// The README's result numbers live in generated blocks only: every `<!-- NAME:begin -->` block is
/// one a test here regenerates, and outside them no table row carries a decimal number and no line
/// a `± number` (the demo's table, typed from runs nobody archived, had both).
#[test]
fn readme_result_numbers_are_in_generated_blocks_only() {
    let readme = read(&repo().join("README.md"));
    let generated = [pdt_repro::render::README_BEGIN];
    for (i, _) in readme.match_indices("<!-- ") {
        let marker = &readme[i..readme[i..].find("-->").map_or(readme.len(), |e| i + e + 3)];
        if marker.ends_with(":begin -->") {
            assert!(generated.contains(&marker), "README.md: {marker} is no block a test checks");
        }
    }
    let decimal = |l: &str| {
        let b = l.as_bytes();
        (1..b.len().saturating_sub(1))
            .any(|i| b[i] == b'.' && b[i - 1].is_ascii_digit() && b[i + 1].is_ascii_digit())
    };
    // `± 0.29`, not `mean ± std`.
    let pm_number = |l: &str| {
        l.match_indices('±').any(|(i, _)| {
            l[i + '±'.len_utf8()..].trim_start().starts_with(|c: char| c.is_ascii_digit())
        })
    };
    let mut inside = false;
    let mut typed = Vec::new();
    for line in readme.lines() {
        if line.contains(pdt_repro::render::README_BEGIN) {
            inside = true;
        } else if line.contains(pdt_repro::render::README_END) {
            inside = false;
        } else if !inside && ((line.starts_with('|') && decimal(line)) || pm_number(line)) {
            typed.push(line);
        }
    }
    assert!(
        typed.is_empty(),
        "README.md: result numbers outside a generated block:\n{}",
        typed.join("\n")
    );
}

/// docs/prompt-control.md's table of the prompt-control rows is generated from the registry
/// (`promptdt results render` rewrites it): regenerated here, it must be the committed one.
#[test]
fn the_prompt_control_docs_table_is_the_generators_output() {
    use pdt_repro::render::{PROMPT_CONTROL_BEGIN, PROMPT_CONTROL_END};
    let root = repo();
    let r = render(&root.join("results")).unwrap_or_else(|e| panic!("render: {e}"));
    let path = root.join("docs/prompt-control.md");
    let doc = read(&path);
    let quoted = block(&doc, PROMPT_CONTROL_BEGIN, PROMPT_CONTROL_END).unwrap_or_else(|| {
        panic!("{}: no {PROMPT_CONTROL_BEGIN} ... {PROMPT_CONTROL_END} block", path.display())
    });
    // Every archived prompt-control column shows up (an empty registry would match an empty block).
    assert!(r.prompt_control_block.contains("| row | cheetah_vel |"), "{}", r.prompt_control_block);
    assert!(
        quoted == r.prompt_control_block,
        "{}: the generated table is stale; run `promptdt results render`",
        path.display()
    );
}

/// A table cell that is a bare measured number (`74.5`, `-22.24`, `1.5 s`): what a typed
/// result looks like in a Markdown table. Settings quoted in prose cells (`lr 1e-3`, arXiv ids)
/// are not bare numbers.
fn bare_number(cell: &str) -> bool {
    let c = cell.trim().trim_end_matches([' ', 's', '%']).trim();
    let c = c.strip_prefix(['-', '+', '−']).unwrap_or(c);
    c.contains('.')
        && !c.is_empty()
        && c.chars().all(|ch| ch.is_ascii_digit() || ch == '.' || ch == ',')
        && c.chars().next().is_some_and(|ch| ch.is_ascii_digit())
}

/// The docs that once typed measured numbers (docs/prompt-control.md's and docs/macaw.md's
/// tables of unarchived or hand-copied runs) have none outside their generated blocks: no table
/// cell that is a bare decimal number, no `± number`.
#[test]
fn docs_type_no_measured_numbers_outside_generated_blocks() {
    assert!(bare_number("74.5") && bare_number(" -22.24 ") && bare_number("1.5 s"));
    assert!(!bare_number("lr 1e-3") && !bare_number("2502.04979 (arXiv)") && !bare_number("20"));
    let blocks = [(pdt_repro::render::PROMPT_CONTROL_BEGIN, pdt_repro::render::PROMPT_CONTROL_END)];
    let mut typed = Vec::new();
    for name in ["docs/prompt-control.md", "docs/macaw.md"] {
        let doc = read(&repo().join(name));
        let mut inside = false;
        for line in doc.lines() {
            if blocks.iter().any(|(b, _)| line.contains(b)) {
                inside = true;
            } else if blocks.iter().any(|(_, e)| line.contains(e)) {
                inside = false;
            } else if !inside {
                let cells = line.starts_with('|').then(|| line.split('|').any(bare_number));
                let pm = line.match_indices('±').any(|(i, _)| {
                    line[i + '±'.len_utf8()..]
                        .trim_start()
                        .starts_with(|c: char| c.is_ascii_digit())
                });
                if cells == Some(true) || pm {
                    typed.push(format!("{name}: {line}"));
                }
            }
        }
    }
    assert!(
        typed.is_empty(),
        "measured numbers typed outside a generated block:\n{}",
        typed.join("\n")
    );
}
