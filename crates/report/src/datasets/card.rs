//! The card check: warnings where `dataset.json` disagrees with the data files.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use pdt_data::native;

use super::ReturnStat;

/// Warns where `dataset.json` disagrees with the files it describes. The card is never used for
/// the numbers; a disagreement means it is stale (files regenerated or edited afterwards).
pub(super) fn check_card(
    dir: &Path,
    stats: &BTreeMap<PathBuf, ReturnStat>,
    warnings: &mut Vec<String>,
) {
    let card = match native::read_card(dir) {
        Ok(Some(card)) => card,
        Ok(None) => return,
        Err(e) => {
            warnings.push(format!("{e} (the card is ignored; returns come from the files)"));
            return;
        }
    };
    let card_path = dir.join(native::CARD_FILE_NAME);
    for file in card.tasks.iter().flat_map(|t| &t.files) {
        if let Some((env, _, _)) = native::parse_task_file_stem(
            file.name.strip_suffix(".safetensors").unwrap_or(&file.name),
        ) {
            if env != card.env {
                warnings.push(format!(
                    "{}: says the data are `{}`'s but lists {} (the card is wrong)",
                    card_path.display(),
                    card.env,
                    file.name
                ));
            }
        }
        let path = dir.join(&file.name);
        let Some(s) = stats.get(&path) else { continue };
        let tol = 1e-6 * s.mean.abs().max(1.0);
        if file.episodes != s.episodes || (file.returns.mean - s.mean).abs() > tol {
            warnings.push(format!(
                "{}: says {} has {} episodes with mean return {:.4}, the file has {} with {:.4}; \
                 the card is stale",
                card_path.display(),
                file.name,
                file.episodes,
                file.returns.mean,
                s.episodes,
                s.mean
            ));
        }
    }
}
