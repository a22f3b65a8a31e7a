//! The dataset card: `dataset.json`, the optional description of a directory's files.

use super::*;

/// The optional `dataset.json` of a directory of native files: what was generated, how, and
/// summary statistics. Written by data-collection code; nothing needs it to read a file.
/// Unknown keys are ignored on reading, so later versions can add fields.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetCard {
    /// Always [`CARD_FORMAT_NAME`].
    #[serde(default = "card_format_name")]
    pub format: String,
    /// Card version; currently [`FORMAT_VERSION`].
    #[serde(default = "card_format_version")]
    pub format_version: String,
    /// Environment family, e.g. `cheetah_vel`.
    pub env: String,
    pub obs_dim: usize,
    pub act_dim: usize,
    pub tasks: Vec<CardTask>,
    /// Free-form description of how the data was made (policy checkpoints, seeds, code version,
    /// simulator version, ...).
    #[serde(default)]
    pub generator: serde_json::Value,
}

fn card_format_name() -> String {
    CARD_FORMAT_NAME.to_owned()
}

fn card_format_version() -> String {
    FORMAT_VERSION.to_owned()
}

/// One task of a [`DatasetCard`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CardTask {
    pub index: usize,
    /// The task's parameters, e.g. `{"target_velocity": 0.225}`.
    #[serde(default)]
    pub params: serde_json::Value,
    pub files: Vec<CardFile>,
}

/// One file of a [`CardTask`], with its summary statistics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CardFile {
    /// File name relative to the card's directory, e.g. `cheetah_vel-2-expert.safetensors`.
    pub name: String,
    /// e.g. `expert`, `prompt-expert`.
    pub mode: String,
    pub episodes: usize,
    pub steps: usize,
    pub returns: ReturnStats,
}

impl CardFile {
    /// Describes a dataset that was (or will be) written under `name`.
    pub fn describe(name: impl Into<String>, mode: impl Into<String>, ds: &TaskDataset) -> Self {
        Self {
            name: name.into(),
            mode: mode.into(),
            episodes: ds.trajectories.len(),
            steps: ds.num_steps(),
            returns: ReturnStats::of(&ds.returns()),
        }
    }
}

/// Undiscounted episode-return statistics (population std, like numpy's default). All zero for an
/// empty list.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReturnStats {
    pub mean: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
}

impl ReturnStats {
    pub fn of(returns: &[f64]) -> Self {
        if returns.is_empty() {
            return Self { mean: 0.0, std: 0.0, min: 0.0, max: 0.0 };
        }
        let n = returns.len() as f64;
        let mean = returns.iter().sum::<f64>() / n;
        let var = returns.iter().map(|r| (r - mean) * (r - mean)).sum::<f64>() / n;
        Self {
            mean,
            std: var.sqrt(),
            min: returns.iter().copied().fold(f64::INFINITY, f64::min),
            max: returns.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        }
    }
}

/// Reads `dir/dataset.json`; `Ok(None)` if the directory has no card.
pub fn read_card(dir: &Path) -> Result<Option<DatasetCard>, DataError> {
    let path = dir.join(CARD_FILE_NAME);
    let text = match pdt_base::fs::read_text_limited(&path, pdt_base::fs::MAX_TEXT_BYTES) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(source) => return Err(DataError::Io { path, source }),
    };
    let card: DatasetCard = serde_json::from_str(&text)
        .map_err(|e| format_err(&path, format!("invalid dataset card: {e}")))?;
    if card.format != CARD_FORMAT_NAME {
        return Err(format_err(
            &path,
            format!("`format` is {:?}, expected {CARD_FORMAT_NAME:?}", card.format),
        ));
    }
    if card.format_version != FORMAT_VERSION {
        return Err(format_err(
            &path,
            format!(
                "`format_version` is {:?}; this reader understands only {FORMAT_VERSION:?}",
                card.format_version
            ),
        ));
    }
    // File names are names in this directory, never paths that lead out of it.
    for f in card.tasks.iter().flat_map(|t| &t.files) {
        // Separators are refused outright: `components()` ignores a trailing `/` ("a/" reads "a").
        let mut parts = Path::new(&f.name).components();
        let plain = !f.name.contains(['/', '\\'])
            && matches!(parts.next(), Some(std::path::Component::Normal(_)))
            && parts.next().is_none();
        if !plain {
            return Err(format_err(
                &path,
                format!("file name {:?} is not a plain file name in this directory", f.name),
            ));
        }
    }
    Ok(Some(card))
}

/// Writes `dir/dataset.json` (pretty-printed, atomically like the data files).
pub fn write_card(dir: &Path, card: &DatasetCard) -> Result<(), DataError> {
    let path = dir.join(CARD_FILE_NAME);
    let mut text = serde_json::to_string_pretty(card)
        .map_err(|e| format_err(&path, format!("cannot serialise the card: {e}")))?;
    text.push('\n');
    write_atomically(&path, |tmp| fs::write(tmp, text.as_bytes()).map_err(io_err(tmp)))
}
