//! How vcedit writes files, in one place:
//!
//! - [`atomic_write`]: a file appears whole or not at all (temporary file + rename); [`replace_folder`]:
//!   the same for an output of several files (a SOG folder), swapped in whole.
//! - `temp`: the one maker of temporary files and folders (exclusive creation, unpredictable names),
//!   [`check_writable_folder`] (an output's folder checked before any work), and [`clean_stale_temps`]
//!   (removes only what killed vcedit runs provably left).
//! - [`check_not_inputs`]: no command writes over one of its inputs or inside an input folder, whatever
//!   the spelling of the paths (`./a.png` vs `a.png`, symbolic links, hard links).
//! - [`RunDir`]: an output folder holds the files of one run: a folder with another run's files is
//!   refused unless it is the same run being resumed, or `--force` clears what vcedit wrote there.
//! - [`open_regular`] / [`read_regular`]: inputs are read only from regular files (a named pipe would
//!   block the reader forever).
//! - [`available_memory`] / [`check_allocation`]: what a run or a reader may allocate (the host's
//!   `MemAvailable`, or a container's cgroup headroom when smaller).
//! - [`cache_dir`]: the one user cache folder for what vcedit can always make again.

mod atomic;
mod cache;
mod memory;
mod paths;
mod regular;
mod rundir;
mod swap;
mod temp;

pub use atomic::{atomic_write, atomic_write_with};
pub use cache::cache_dir;
pub use memory::{available_memory, check_allocation};
pub use paths::{check_not_inputs, same_file, PathError};
pub use regular::{check_regular, open_regular, read_regular};
pub use rundir::{Previous, RunDir, RunDirError, RunDirMode, MANIFEST_NAME};
pub use swap::replace_folder;
pub use temp::{check_writable_folder, clean_stale_temps, is_temporary_name};
