//! One way to open an input: only regular files (after links). A named pipe would block the reader
//! until some other program writes to it (forever, usually), and a device or socket never ends; both are
//! refused with an error that says what the path is.

use std::fs::File;
use std::io;
use std::path::Path;

/// What a path that is not a regular file is, in words.
fn kind(meta: &std::fs::Metadata) -> &'static str {
    let ty = meta.file_type();
    if ty.is_dir() {
        return "a folder";
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if ty.is_fifo() {
            return "a named pipe";
        }
        if ty.is_socket() {
            return "a socket";
        }
        if ty.is_char_device() || ty.is_block_device() {
            return "a device";
        }
    }
    "not a regular file"
}

/// Checks that `path` is a regular file (links followed) without opening it.
pub fn check_regular(path: &Path) -> io::Result<()> {
    let meta = std::fs::metadata(path)?;
    if meta.is_file() {
        return Ok(());
    }
    Err(io::Error::new(
        io::ErrorKind::InvalidInput,
        format!("not a regular file: it is {}", kind(&meta)),
    ))
}

/// Opens `path` for reading when it is a regular file.
pub fn open_regular(path: &Path) -> io::Result<File> {
    check_regular(path)?;
    File::open(path)
}

/// Reads `path` whole when it is a regular file whose size fits in memory (a sparse file can claim
/// terabytes without taking the space; reading it would fail to allocate and abort).
pub fn read_regular(path: &Path) -> io::Result<Vec<u8>> {
    check_regular(path)?;
    let len = std::fs::metadata(path)?.len();
    crate::check_allocation(len, &format!("its {len} bytes"))
        .map_err(|msg| io::Error::new(io::ErrorKind::OutOfMemory, msg))?;
    std::fs::read(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_folders_and_pipes_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.bin");
        std::fs::write(&file, b"abc").unwrap();
        assert_eq!(read_regular(&file).unwrap(), b"abc");
        let e = open_regular(dir.path()).unwrap_err().to_string();
        assert!(e.contains("a folder"), "{e}");
        assert_eq!(
            check_regular(&dir.path().join("missing"))
                .unwrap_err()
                .kind(),
            io::ErrorKind::NotFound
        );
        #[cfg(unix)]
        {
            let fifo = dir.path().join("pipe");
            let made = std::process::Command::new("mkfifo").arg(&fifo).status();
            if made.is_ok_and(|s| s.success()) {
                // Opening a FIFO for reading would block here without a writer: the check must not open it.
                let e = read_regular(&fifo).unwrap_err().to_string();
                assert!(e.contains("a named pipe"), "{e}");
            }
        }
    }

    #[test]
    fn a_sparse_file_larger_than_memory_is_refused_before_reading() {
        let Some(available) = crate::available_memory() else {
            return;
        };
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("sparse.bin");
        let f = std::fs::File::create(&p).unwrap();
        if f.set_len(available.saturating_mul(2).max(1 << 36)).is_err() {
            return; // a file system without sparse files this large
        }
        let e = read_regular(&p).unwrap_err().to_string();
        assert!(e.contains("memory available"), "{e}");
    }
}
