//! Writes the `[reference_experts]` tables of the committed manifests (`experiments/*.toml`) from
//! the reference release's prompt files, so the numbers are generated, never typed:
//!
//! ```sh
//! cargo run --release -p pdt-repro --example reference_experts -- ../shared/data/official-prompts
//! cargo run --release -p pdt-repro --example reference_experts -- DIR --check   # changes nothing
//! ```
//!
//! Each manifest with a cell in a family the release has prompt files for
//! (`manifest::REFERENCE_ENVS`) gets the tables of those families, between its
//! `# BEGIN reference_experts` and `# END reference_experts` lines (appended at the end the first
//! time); a manifest without such cells loses the block. `--check` exits 1 if a file would change.

use pdt_repro::manifest::{render_reference_experts, Manifest, BUILTIN, REFERENCE_ENVS};
use std::path::{Path, PathBuf};

const BEGIN: &str = "# BEGIN reference_experts";
const END: &str = "# END reference_experts\n";

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let check = args.iter().any(|a| a == "--check");
    let dirs: Vec<&String> = args.iter().filter(|a| *a != "--check").collect();
    let [dir] = dirs[..] else {
        return Err("usage: reference_experts OFFICIAL_PROMPTS_DIR [--check]".into());
    };
    let experiments = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../experiments");
    let mut stale = Vec::new();
    for (name, _) in BUILTIN {
        let path: PathBuf = experiments.join(format!("{name}.toml"));
        let text =
            std::fs::read_to_string(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        let m = Manifest::parse(&text, name)?;
        let envs: Vec<&str> = REFERENCE_ENVS
            .into_iter()
            .filter(|env| m.cells.iter().any(|c| c.pending.is_none() && c.env == *env))
            .collect();
        // The file without its block (and the blank line before it), then the new block.
        let mut rest = text.clone();
        if let Some(start) = text.find(BEGIN) {
            let end = text[start..]
                .find(END)
                .map(|e| start + e + END.len())
                .ok_or_else(|| format!("{}: {BEGIN} without {}", path.display(), END.trim()))?;
            rest = format!("{}{}", text[..start].trim_end_matches('\n'), &text[end..]);
        }
        // One newline at the end, then a blank line before the block: a second run changes nothing.
        rest = format!("{}\n", rest.trim_end_matches('\n'));
        let new = match envs.is_empty() {
            // Nothing to write: a file that never had a block stays as it is.
            true if !text.contains(BEGIN) => text.clone(),
            true => rest,
            false => format!("{rest}\n{}", render_reference_experts(Path::new(dir), &envs)?),
        };
        // The result must still be a valid manifest with the numbers in it.
        Manifest::parse(&new, name)?;
        if new != text {
            stale.push(format!("experiments/{name}.toml"));
            if !check {
                pdt_base::fs::write_atomic(&path, new.as_bytes())
                    .map_err(|e| format!("{}: {e}", path.display()))?;
            }
        }
    }
    match (check, stale.is_empty()) {
        (_, true) => println!("every manifest's reference_experts is up to date"),
        (false, false) => println!("wrote {}", stale.join(", ")),
        (true, false) => return Err(format!("out of date: {}", stale.join(", ")).into()),
    }
    Ok(())
}
