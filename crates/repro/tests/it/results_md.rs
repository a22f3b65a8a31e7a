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
