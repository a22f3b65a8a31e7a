//! Flat step arrays from an HDF5 file: the D4RL layout (`observations`, `actions`, `rewards`,
//! `terminals`, `timeouts` at the root, any other datasets beside them) plus a task column, read
//! by a pure-Rust decoder (`hdf5-reader`), so a user needs no libhdf5. Numbers of any width are
//! taken (h5py writes numpy's bools as an enum of int8, D4RL's rewards are float32, a task column
//! may be int64); the checks of [`FlatSteps::split_by_task`] then run as for an `.npz`.

use crate::flat::FlatSteps;
use crate::DataError;
use hdf5_reader::{Dataset, Datatype, Hdf5File};
use std::path::{Path, PathBuf};

/// The datasets a flat file must hold besides its task column.
const STEP_FIELDS: [&str; 5] = ["observations", "actions", "rewards", "terminals", "timeouts"];

/// A flat HDF5 file read: its steps and the datasets in it that were not read (D4RL files carry
/// `next_observations`, `infos/...`, `metadata/...`), so the caller can say what it left out.
#[derive(Debug, Clone, PartialEq)]
pub struct FlatHdf5 {
    pub steps: FlatSteps,
    pub ignored: Vec<String>,
}

fn bad(path: &Path, message: String) -> DataError {
    DataError::Format { path: PathBuf::from(path), message }
}

/// Reads `path`'s step arrays, each checked against the sizes given: observations `[N,
/// obs_dim]`, actions `[N, act_dim]`, rewards/terminals/timeouts `[N]` (or `[N, 1]`), and the
/// task of each step from the dataset `task_field` (a path inside the file, e.g. `task_ids` or
/// `infos/task`), whole numbers.
pub fn read_flat_hdf5(
    path: &Path,
    obs_dim: usize,
    act_dim: usize,
    task_field: &str,
) -> Result<FlatHdf5, DataError> {
    let file =
        Hdf5File::open(path).map_err(|e| bad(path, format!("not a readable HDF5 file ({e})")))?;
    let take = |field: &str, width: Option<usize>| -> Result<Dataset, DataError> {
        let ds = file.dataset(field).map_err(|_| {
            bad(
                path,
                format!(
                    "no dataset `{field}` (a flat dataset has observations, actions, rewards, \
                     terminals, timeouts and a task column, `{task_field}`)"
                ),
            )
        })?;
        crate::flat::check_column_shape(path, field, ds.shape(), width)?;
        Ok(ds)
    };
    let observations = floats(path, "observations", &take("observations", Some(obs_dim))?)?;
    let actions = floats(path, "actions", &take("actions", Some(act_dim))?)?;
    let rewards = floats(path, "rewards", &take("rewards", None)?)?;
    let terminals = flags(path, "terminals", &take("terminals", None)?)?;
    let timeouts = flags(path, "timeouts", &take("timeouts", None)?)?;
    let task_ids = whole(path, task_field, &take(task_field, None)?)?;
    let read: Vec<&str> = STEP_FIELDS.iter().copied().chain([task_field]).collect();
    let ignored =
        dataset_paths(&file, path)?.into_iter().filter(|p| !read.contains(&p.as_str())).collect();
    let steps = FlatSteps {
        obs_dim,
        act_dim,
        observations,
        actions,
        rewards,
        terminals,
        timeouts,
        task_ids,
    };
    Ok(FlatHdf5 { steps, ignored })
}

/// Every dataset's path in the file, groups walked depth first.
fn dataset_paths(file: &Hdf5File, path: &Path) -> Result<Vec<String>, DataError> {
    let walk_err = |e: hdf5_reader::error::Error| bad(path, format!("reading its groups: {e}"));
    let mut out = vec![];
    let mut stack = vec![(String::new(), file.root_group().map_err(walk_err)?)];
    while let Some((prefix, group)) = stack.pop() {
        for ds in group.datasets().map_err(walk_err)? {
            out.push(format!("{prefix}{}", ds.name().trim_start_matches('/')));
        }
        for g in group.groups().map_err(walk_err)? {
            let name = format!("{prefix}{}/", g.name().trim_start_matches('/'));
            stack.push((name, g));
        }
    }
    out.sort();
    Ok(out)
}

/// A dataset's values as f64, whatever numeric type it holds.
fn numbers(path: &Path, field: &str, ds: &Dataset) -> Result<Vec<f64>, DataError> {
    let read_err = |e: hdf5_reader::error::Error| bad(path, format!("reading `{field}`: {e}"));
    macro_rules! as_f64 {
        ($t:ty) => {
            ds.read_array::<$t>().map_err(read_err)?.iter().map(|&x| x as f64).collect()
        };
    }
    let dtype = match ds.dtype() {
        // numpy's bool (h5py: an enum FALSE/TRUE over int8) and other enums: their integers.
        Datatype::Enum { base, .. } => base.as_ref(),
        d => d,
    };
    Ok(match dtype {
        Datatype::FloatingPoint { size: 4, .. } => as_f64!(f32),
        Datatype::FloatingPoint { size: 8, .. } => as_f64!(f64),
        Datatype::FixedPoint { size: 1, signed: true, .. } => raw_ints::<i8>(ds, read_err)?,
        Datatype::FixedPoint { size: 1, signed: false, .. } => raw_ints::<u8>(ds, read_err)?,
        Datatype::FixedPoint { size: 2, signed: true, .. } => as_f64!(i16),
        Datatype::FixedPoint { size: 2, signed: false, .. } => as_f64!(u16),
        Datatype::FixedPoint { size: 4, signed: true, .. } => as_f64!(i32),
        Datatype::FixedPoint { size: 4, signed: false, .. } => as_f64!(u32),
        Datatype::FixedPoint { size: 8, signed: true, .. } => as_f64!(i64),
        Datatype::FixedPoint { size: 8, signed: false, .. } => as_f64!(u64),
        other => {
            return Err(bad(path, format!("`{field}` holds {other:?} values; expected numbers")))
        }
    })
}

/// One-byte integers: read as such when the type is a plain integer, from the raw bytes when it
/// is an enum over one (the typed read refuses an enum).
fn raw_ints<T: hdf5_reader::H5Type + Into<f64> + Copy + FromByte>(
    ds: &Dataset,
    read_err: impl Fn(hdf5_reader::error::Error) -> DataError,
) -> Result<Vec<f64>, DataError> {
    match ds.dtype() {
        Datatype::Enum { .. } => {
            Ok(ds.read_raw_bytes().map_err(read_err)?.into_iter().map(T::from_byte).collect())
        }
        _ => Ok(ds.read_array::<T>().map_err(read_err)?.iter().map(|&x| x.into()).collect()),
    }
}

/// A one-byte integer from its byte.
trait FromByte {
    fn from_byte(b: u8) -> f64;
}
impl FromByte for i8 {
    fn from_byte(b: u8) -> f64 {
        f64::from(b as i8)
    }
}
impl FromByte for u8 {
    fn from_byte(b: u8) -> f64 {
        f64::from(b)
    }
}

fn floats(path: &Path, field: &str, ds: &Dataset) -> Result<Vec<f32>, DataError> {
    Ok(numbers(path, field, ds)?.into_iter().map(|x| x as f32).collect())
}

fn flags(path: &Path, field: &str, ds: &Dataset) -> Result<Vec<bool>, DataError> {
    Ok(numbers(path, field, ds)?.into_iter().map(|x| x != 0.0).collect())
}

fn whole(path: &Path, field: &str, ds: &Dataset) -> Result<Vec<i64>, DataError> {
    if matches!(ds.dtype(), Datatype::FloatingPoint { .. }) {
        return Err(bad(
            path,
            format!("`{field}` holds floating-point values; expected whole numbers"),
        ));
    }
    Ok(numbers(path, field, ds)?.into_iter().map(|x| x as i64).collect())
}
