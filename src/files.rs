//! Files written whole or not at all: below both the CLI and the node.

use std::io;
use std::path::{Path, PathBuf};

/// Writes `bytes` to `path` through a `.partial` file renamed into place, so a reader
/// never sees half a file and a failed write leaves the old one.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let tmp = partial_path(path);
    std::fs::write(&tmp, bytes).map_err(|e| io::Error::new(e.kind(), format!("writing {}: {e}", tmp.display())))?;
    std::fs::rename(&tmp, path).map_err(|e| {
        io::Error::new(
            e.kind(),
            format!("renaming {} to {}: {e}", tmp.display(), path.display()),
        )
    })
}

/// `path` with `.partial` appended: where a file is written before it is renamed into place.
pub fn partial_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(".partial");
    PathBuf::from(s)
}
