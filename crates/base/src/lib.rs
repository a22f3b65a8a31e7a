//! The plumbing every promptdt crate shares, in one place so it behaves the same everywhere:
//!
//! - [`fs`]: files written atomically (temp file, fsync, rename), files read with a size limit and
//!   only when they are regular files (a FIFO or `/dev/zero` is refused, not read forever), the
//!   temporary files a killed writer left behind, and the lock that gives a run directory one owner.
//! - [`seed`]: independent seeds for every random choice, derived from one seed.
//! - [`num`]: numbers as messages print them (1e300, not its 301 digits).
//! - [`device`]: the device a configuration asks for (`cpu`, `cuda`, `auto`), without libtorch.
//! - [`random`]: standard normal samples (Box-Muller) from any uniform source.
//! - [`threads`]: thread-count settings where 0 means all cores.
//! - [`table`]: Markdown and aligned plain-text tables.
//! - [`stop`]: a request to stop a long call early (Ctrl-C from a front end).
//! - [`tensor_file`]: what is wrong with a safetensors file, in plain words.

pub mod device;
pub mod fs;
pub mod num;
pub mod random;
pub mod seed;
pub mod stop;
pub mod table;
pub mod tensor_file;
pub mod threads;

pub use random::standard_normal;
pub use threads::threads;
