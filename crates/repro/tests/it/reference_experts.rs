//! The reference experts' returns committed in `experiments/*.toml` (`[reference_experts]`) are
//! what the reference release's prompt files give: recomputed from the files when they are present
//! (`pdt_testkit::reference`), and the committed block is byte for byte what the generator
//! (`examples/reference_experts.rs`) writes, so nobody edited a number by hand.

use pdt_repro::manifest::{
    reference_expert_return, render_reference_experts, Manifest, BUILTIN, REFERENCE_ENVS,
};

#[test]
fn committed_reference_experts_match_the_release_files() {
    let Some(dir) = pdt_testkit::reference::official_prompts() else { return };
    let mut checked = 0;
    for (name, text) in BUILTIN {
        let m = Manifest::parse(text, name).unwrap_or_else(|e| panic!("{name}: {e}"));
        for (env, committed) in &m.reference_experts {
            for (t, &want) in committed.returns.iter().enumerate() {
                let got = reference_expert_return(&dir, env, t).unwrap_or_else(|e| panic!("{e}"));
                // Exact: the manifest holds the shortest decimal that parses back to the same f64.
                assert_eq!(want, got, "{name}: reference_experts.{env}.returns[{t}]");
                checked += 1;
            }
        }
        let envs: Vec<&str> =
            REFERENCE_ENVS.into_iter().filter(|e| m.reference_experts.contains_key(*e)).collect();
        if envs.is_empty() {
            assert!(!text.contains("# BEGIN reference_experts"), "{name}");
            continue;
        }
        let block = render_reference_experts(&dir, &envs).unwrap_or_else(|e| panic!("{e}"));
        assert!(
            text.contains(&block),
            "{name}.toml: its reference_experts block is not the generator's output; run \
             `cargo run --release -p pdt-repro --example reference_experts -- {}`",
            dir.display()
        );
    }
    // fig2 and table1 at least carry both families (2 + 40 tasks each).
    assert!(checked >= 2 * 42, "only {checked} numbers checked");
}

#[test]
fn the_figures_are_the_readme_s() {
    // shared/data/README.md: cheetah_dir-0 (forward) returns 630-687, cheetah_dir-1 (backward)
    // 1129-1171; a manifest's numbers outside them would be another file's or another statistic.
    let m = Manifest::load("fig2").unwrap_or_else(|e| panic!("{e}"));
    let dir = &m.reference_experts["cheetah_dir"].returns;
    assert!((630.0..=687.0).contains(&dir[0]) && (1129.0..=1171.0).contains(&dir[1]), "{dir:?}");
    let vel = &m.reference_experts["cheetah_vel"].returns;
    assert!((-16.25..=-15.65).contains(&vel[2]) && (-57.75..=-56.55).contains(&vel[39]), "{vel:?}");
}
