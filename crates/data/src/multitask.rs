//! Loading D_i and P_i for a list of tasks from a directory laid out like the reference release
//! (`{dir}/{env}-{i}-{dataset_mode}.pkl`, `{dir}/{env}-{i}-prompt-{prompt_mode}.pkl`), in the native
//! format, the reference's pickles, or a mix; and converting a directory of pickles to the native
//! format.

use std::fs;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::native::{self, FileMeta};
use crate::{DataError, MultiTaskDataset, TaskData, TaskDataset, TaskId};

/// Extension of the reference release's pickle files (without the dot).
pub const PICKLE_EXTENSION: &str = "pkl";

/// Which file format to load.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DataFormat {
    /// `.safetensors` files only.
    Native,
    /// The reference release's `.pkl` files only.
    ReferencePickle,
    /// Per file: `.safetensors` if it exists, else `.pkl`.
    #[default]
    Auto,
}

impl DataFormat {
    /// Candidate extensions, in order of preference.
    fn extensions(self) -> &'static [&'static str] {
        match self {
            DataFormat::Native => &[native::FILE_EXTENSION],
            DataFormat::ReferencePickle => &[PICKLE_EXTENSION],
            DataFormat::Auto => &[native::FILE_EXTENSION, PICKLE_EXTENSION],
        }
    }
}

impl std::fmt::Display for DataFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            DataFormat::Native => "native",
            DataFormat::ReferencePickle => "reference-pickle",
            DataFormat::Auto => "auto",
        })
    }
}

impl std::str::FromStr for DataFormat {
    type Err = String;

    /// Accepts the names `Display` prints, plus `safetensors` and `pickle` / `pkl`.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "native" | "safetensors" => Ok(DataFormat::Native),
            "reference-pickle" | "pickle" | "pkl" => Ok(DataFormat::ReferencePickle),
            "auto" => Ok(DataFormat::Auto),
            other => Err(format!(
                "unknown data format {other:?}; expected native, reference-pickle or auto"
            )),
        }
    }
}

/// Where and what to load: D_i from `{dir}/{env}-{i}-{dataset_mode}.{ext}` and P_i from
/// `{dir}/{env}-{i}-prompt-{prompt_mode}.{ext}` for every `i` in `tasks`, in that order.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DatasetSpec {
    pub dir: PathBuf,
    /// Environment family, e.g. `cheetah_vel`.
    pub env: String,
    /// Task indices, e.g. the train split.
    pub tasks: Vec<usize>,
    /// Kind of the main dataset D_i, e.g. `expert` (the reference's `--dataset_mode`).
    pub dataset_mode: String,
    /// Kind of the prompt set P_i without the `prompt-` prefix, e.g. `expert` (the reference's
    /// `--train_prompt_mode` / `--test_prompt_mode`).
    pub prompt_mode: String,
    pub format: DataFormat,
}

impl DatasetSpec {
    /// The reference's defaults: expert D_i and expert P_i, any format.
    pub fn new(dir: impl Into<PathBuf>, env: impl Into<String>, tasks: Vec<usize>) -> Self {
        Self {
            dir: dir.into(),
            env: env.into(),
            tasks,
            dataset_mode: "expert".into(),
            prompt_mode: "expert".into(),
            format: DataFormat::Auto,
        }
    }

    /// The mode string of P_i files: `prompt-{prompt_mode}`.
    pub fn prompt_file_mode(&self) -> String {
        format!("prompt-{}", self.prompt_mode)
    }
}

/// Finds the file of task `index` and kind `mode` in `dir`: `{env}-{index}-{mode}.{ext}` for the
/// extensions `format` allows, first existing one wins. The error lists every path tried.
pub fn resolve_task_file(
    dir: &Path,
    env: &str,
    index: usize,
    mode: &str,
    format: DataFormat,
) -> Result<PathBuf, DataError> {
    // A missing directory (or a symlink loop) is named as such, not as "no data for task ...".
    match fs::metadata(dir) {
        Ok(m) if m.is_dir() => {}
        Ok(_) => {
            return Err(DataError::Format {
                path: dir.to_path_buf(),
                message: "not a directory (data.dir must name the directory of the task files)"
                    .into(),
            })
        }
        Err(source) => return Err(DataError::Io { path: dir.to_path_buf(), source }),
    }
    let stem = native::task_file_stem(env, index, mode);
    let tried: Vec<PathBuf> =
        format.extensions().iter().map(|ext| dir.join(format!("{stem}.{ext}"))).collect();
    for candidate in &tried {
        // Only a name that does not exist at all moves on to the next extension. Anything else
        // under the data file's name (a directory, a FIFO, a symlink loop or a dangling link) is
        // named as what it is: "no data" would send the user looking for a missing file.
        match fs::metadata(candidate) {
            Ok(m) if m.is_file() => return Ok(candidate.clone()),
            Ok(m) => {
                return Err(DataError::Format {
                    path: candidate.clone(),
                    message: format!(
                        "is {}, not a data file (expected the {mode} data of task {env}-{index})",
                        file_kind(&m.file_type())
                    ),
                })
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                if fs::symlink_metadata(candidate).is_ok() {
                    return Err(DataError::Format {
                        path: candidate.clone(),
                        message: "is a symbolic link to a file that does not exist".into(),
                    });
                }
            }
            Err(source) => return Err(DataError::Io { path: candidate.clone(), source }),
        }
    }
    // The directory is the error's path; the names tried are listed without it, so the message
    // names the directory once.
    let list: Vec<String> = format.extensions().iter().map(|ext| format!("{stem}.{ext}")).collect();
    Err(DataError::Format {
        path: dir.to_path_buf(),
        message: format!(
            "no {mode} data for task {env}-{index} (format {format}): tried {} in this directory",
            list.join(" and ")
        ),
    })
}

/// What a non-regular file is, for messages.
pub(crate) fn file_kind(ft: &fs::FileType) -> &'static str {
    if ft.is_dir() {
        return "a directory";
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if ft.is_fifo() {
            return "a FIFO (named pipe)";
        } else if ft.is_char_device() || ft.is_block_device() {
            return "a device";
        } else if ft.is_socket() {
            return "a socket";
        }
    }
    "not a regular file"
}

/// Refuses a native file whose metadata says it holds another task's data than its name: the
/// loader finds files by name, so such a file would silently train the wrong task. Each field
/// the metadata states must agree with the name; a field it leaves out is not checked (files
/// written by hand may carry no metadata).
pub fn check_meta_matches_name(
    path: &Path,
    meta: &FileMeta,
    env: &str,
    index: usize,
    mode: &str,
) -> Result<(), DataError> {
    let mut wrong = Vec::new();
    if let Some(e) = meta.env.as_deref().filter(|e| *e != env) {
        wrong.push(format!("`{}` is {e:?} but the name says {env:?}", native::meta_keys::ENV));
    }
    if let Some(i) = meta.task_index.filter(|i| *i != index) {
        wrong.push(format!("`{}` is {i} but the name says {index}", native::meta_keys::TASK_INDEX));
    }
    if let Some(m) = meta.mode.as_deref().filter(|m| *m != mode) {
        wrong.push(format!("`{}` is {m:?} but the name says {mode:?}", native::meta_keys::MODE));
    }
    if wrong.is_empty() {
        return Ok(());
    }
    Err(DataError::Format {
        path: path.to_path_buf(),
        message: format!(
            "the file's metadata contradicts its name: {} (another task's data under this name; \
             rename the file or fix its metadata)",
            wrong.join("; ")
        ),
    })
}

/// Loads one file, choosing the reader by extension: `.safetensors` (native) or `.pkl`
/// (reference pickle, read without executing code).
pub fn load_task_file(path: &Path) -> Result<TaskDataset, DataError> {
    match path.extension().and_then(|e| e.to_str()) {
        Some(native::FILE_EXTENSION) => native::read_task_dataset(path),
        Some(PICKLE_EXTENSION) => load_reference_pickle(path),
        _ => Err(DataError::Format {
            path: path.to_path_buf(),
            message: format!(
                "unknown file type: expected a .{} or .{PICKLE_EXTENSION} file",
                native::FILE_EXTENSION
            ),
        }),
    }
}

fn load_reference_pickle(path: &Path) -> Result<TaskDataset, DataError> {
    // `load_pickle`'s errors already name the file.
    let loaded =
        crate::reference::load_pickle(path, &crate::reference::ReferenceOptions::default())?;
    Ok(loaded.dataset)
}

/// Loads D_i and P_i for every task of `spec`, in the order of `spec.tasks`. All files must share
/// `obs_dim` and `act_dim`.
pub fn load_multitask(spec: &DatasetSpec) -> Result<MultiTaskDataset, DataError> {
    if spec.tasks.is_empty() {
        return Err(DataError::Format {
            path: spec.dir.clone(),
            message: format!("no tasks given for {}", spec.env),
        });
    }
    let prompt_mode = spec.prompt_file_mode();
    let mut tasks = Vec::with_capacity(spec.tasks.len());
    // The first file fixes the dims; a later file that disagrees is named with the first.
    let mut first: Option<(PathBuf, usize, usize)> = None;
    for &index in &spec.tasks {
        let mut load = |mode: &str| -> Result<TaskDataset, DataError> {
            let path = resolve_task_file(&spec.dir, &spec.env, index, mode, spec.format)?;
            let d = if path.extension().and_then(|e| e.to_str()) == Some(native::FILE_EXTENSION) {
                let (d, meta) = native::read_task_dataset_with_meta(&path)?;
                check_meta_matches_name(&path, &meta, &spec.env, index, mode)?;
                d
            } else {
                // A reference pickle carries no metadata: its name is all there is.
                load_task_file(&path)?
            };
            match &first {
                None => first = Some((path.clone(), d.obs_dim, d.act_dim)),
                Some((p, o, a)) if (*o, *a) != (d.obs_dim, d.act_dim) => {
                    return Err(DataError::Format {
                        path,
                        message: format!(
                            "obs/act dims {}/{}, but {} has {o}/{a} (all files of a run must agree)",
                            d.obs_dim,
                            d.act_dim,
                            p.display()
                        ),
                    })
                }
                Some(_) => {}
            }
            d.check_values().map_err(|message| DataError::Format { path, message })?;
            Ok(d)
        };
        let dataset = load(&spec.dataset_mode)?;
        let prompts = load(&prompt_mode)?;
        tasks.push(TaskData { id: TaskId { env: spec.env.clone(), index }, dataset, prompts });
    }
    let set = MultiTaskDataset::new(tasks).map_err(|e| e.in_file(&spec.dir))?;
    // A card that contradicts the files (another family, other dims) means the directory is not
    // what it claims to be: refuse rather than train on it silently.
    if let Some(card) = native::read_card(&spec.dir)? {
        let path = spec.dir.join(native::CARD_FILE_NAME);
        if card.env != spec.env {
            return Err(DataError::Format {
                path,
                message: format!(
                    "describes `{}` data, but the files read are `{}`'s",
                    card.env, spec.env
                ),
            });
        }
        if (card.obs_dim, card.act_dim) != (set.obs_dim, set.act_dim) {
            return Err(DataError::Format {
                path,
                message: format!(
                    "says obs/act dims {}/{}, but the files have {}/{}",
                    card.obs_dim, card.act_dim, set.obs_dim, set.act_dim
                ),
            });
        }
    }
    Ok(set)
}

/// One file converted by [`convert_reference_dir`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConvertedFile {
    pub source: PathBuf,
    pub dest: PathBuf,
    /// Parsed from the file name; fields are `None` when it does not follow
    /// `{env}-{index}-{mode}`.
    pub meta: FileMeta,
    pub trajectories: usize,
    pub steps: usize,
    pub obs_dim: usize,
    pub act_dim: usize,
}

/// `promptdt data convert`'s line for the file: where from, where to, how much.
impl std::fmt::Display for ConvertedFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (from, to) = (self.source.display(), self.dest.display());
        write!(f, "{from} -> {to} ({} trajectories, {} steps)", self.trajectories, self.steps)
    }
}

/// Converts every `*.pkl` file directly in `src` (not in subdirectories) into
/// `dst/{same stem}.safetensors`, with the metadata parsed from the name `{env}-{index}-{mode}`.
/// Creates `dst` if needed; `dst` may equal `src`. Files are processed in name order and each is
/// written atomically, so a failure leaves earlier conversions complete and no partial file.
pub fn convert_reference_dir(src: &Path, dst: &Path) -> Result<Vec<ConvertedFile>, DataError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| DataError::Io { path, source }
    };
    let mut sources = Vec::new();
    for entry in fs::read_dir(src).map_err(io(src))? {
        let path = entry.map_err(io(src))?.path();
        if path.is_file() && path.extension().and_then(|e| e.to_str()) == Some(PICKLE_EXTENSION) {
            sources.push(path);
        }
    }
    if sources.is_empty() {
        return Err(DataError::Format {
            path: src.to_path_buf(),
            message: format!("no .{PICKLE_EXTENSION} files to convert"),
        });
    }
    sources.sort();
    fs::create_dir_all(dst).map_err(io(dst))?;
    let mut converted = Vec::with_capacity(sources.len());
    for source in sources {
        let dataset = load_reference_pickle(&source)?;
        let meta = FileMeta::from_file_name(&source).unwrap_or_default();
        // `file_stem` exists: the path was listed as a file with an extension.
        let stem = source.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let dest = dst.join(format!("{stem}.{}", native::FILE_EXTENSION));
        native::write_task_dataset(&dest, &dataset, &meta)?;
        converted.push(ConvertedFile {
            source,
            dest,
            meta,
            trajectories: dataset.trajectories.len(),
            steps: dataset.num_steps(),
            obs_dim: dataset.obs_dim,
            act_dim: dataset.act_dim,
        });
    }
    Ok(converted)
}
