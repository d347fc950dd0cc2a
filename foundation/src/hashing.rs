//! Content digests of inputs: BLAKE3 over a folder's files, in a stable order, so a changed,
//! added or removed file changes the digest (shard stats markers, corpus resume, `nvs.json`).

use std::io::Read;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// BLAKE3 over every file under `root` (or the file `root`), in a stable order.
pub fn hash_tree(root: &Path) -> Result<String> {
    let mut files = Vec::new();
    files_under(root, &mut files)?;
    hash_files(files)
}

/// Appends every file under `root` (or the file `root`) to `files`, in no particular order.
pub fn files_under(root: &Path, files: &mut Vec<PathBuf>) -> Result<()> {
    let mut pending = vec![root.to_owned()];
    while let Some(path) = pending.pop() {
        if path.is_dir() {
            let entries = std::fs::read_dir(&path).map_err(|e| Error::io(&path, e))?;
            pending.extend(entries.filter_map(|e| e.ok().map(|e| e.path())));
        } else {
            files.push(path);
        }
    }
    Ok(())
}

/// BLAKE3 over `files` (each file's name, then its bytes) in sorted order, duplicates once: the
/// same set of files gives the same digest however it was listed.
pub fn hash_files(mut files: Vec<PathBuf>) -> Result<String> {
    files.sort();
    files.dedup();
    let mut hasher = blake3::Hasher::new();
    let mut buffer = vec![0u8; 1 << 20];
    for path in files {
        hasher.update(path.file_name().unwrap_or_default().as_encoded_bytes());
        let mut file = std::fs::File::open(&path).map_err(|e| Error::io(&path, e))?;
        loop {
            let read = file.read(&mut buffer).map_err(|e| Error::io(&path, e))?;
            if read == 0 {
                break;
            }
            hasher.update(&buffer[..read]);
        }
    }
    Ok(hasher.finalize().to_hex().to_string())
}
