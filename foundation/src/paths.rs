//! Names read from files, made into paths only when they stay inside their folder, and folders
//! told apart by what they are rather than how they are spelled.
//!
//! A dataset file that lists items by name (DyCheck's `dataset.json` ids, COLMAP's image names,
//! a benchmark's scene names) hands the reader a string it then joins to a folder. Joined
//! unchecked, `../../x/0_00001` or `/etc/passwd` opens a file outside the scene (`Path::join`
//! with an absolute name even replaces the folder). [`join_inside`] is the one door every reader
//! goes through: a name is a relative path of plain components (sub-folders allowed, as COLMAP's
//! `cam1/0001.png`), never `..`, a root or a drive prefix, never empty and never holding a NUL;
//! otherwise the error names the file that listed it and the entry.
//!
//! [`FolderIdentity`] is a folder's canonical path: two spellings of one folder (a link
//! `cam02 -> cam00`, a `loop -> .` in a tree) have the same identity, so a crawl can follow each
//! real folder once and a reader can refuse the same camera listed twice.

use std::path::{Component, Path, PathBuf};

use crate::error::{Error, Result};

/// Whether `name` is a relative path of plain components: what [`join_inside`] accepts.
/// Returns the reason it is not.
pub fn check_name(name: &str) -> std::result::Result<(), String> {
    if name.is_empty() {
        return Err("an empty name".to_string());
    }
    if name.contains('\0') {
        return Err(format!("`{}` holds a NUL byte", name.escape_debug()));
    }
    for component in Path::new(name).components() {
        match component {
            Component::Normal(_) | Component::CurDir => {}
            Component::ParentDir => {
                return Err(format!("`{name}` climbs out of its folder (`..`): names must stay inside it"));
            }
            Component::RootDir | Component::Prefix(_) => {
                return Err(format!("`{name}` is an absolute path: names must be relative to their folder"));
            }
        }
    }
    Ok(())
}

/// `folder/name` for a `name` read from `file` at `entry` (a key, index or line), refused with an
/// [`Error::InvalidInput`] naming both when the name would leave `folder` (see the module docs).
pub fn join_inside(folder: &Path, name: &str, file: &Path, entry: &str) -> Result<PathBuf> {
    check_name(name).map_err(|reason| Error::invalid(file, entry, reason))?;
    Ok(folder.join(name))
}

/// A folder's identity: its canonical path (links resolved), or the path as given when it cannot
/// be resolved (it does not exist; reading it will then name it).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct FolderIdentity(PathBuf);

impl FolderIdentity {
    /// The identity of `path`.
    pub fn of(path: &Path) -> Self {
        Self(std::fs::canonicalize(path).unwrap_or_else(|_| path.to_owned()))
    }

    /// The canonical path.
    pub fn path(&self) -> &Path {
        &self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_and_nested_names_join_inside() {
        let folder = Path::new("/data/scene");
        for name in ["0_00001", "cam1/0001.png", "./a.png", "a..b", "..x"] {
            assert_eq!(join_inside(folder, name, Path::new("f.json"), "ids[0]").unwrap(), folder.join(name));
        }
    }

    #[test]
    fn names_leaving_the_folder_are_refused_naming_file_and_entry() {
        for name in ["../x", "a/../../x", "/etc/passwd", "", "a\0b", ".."] {
            let error = join_inside(Path::new("/s"), name, Path::new("dataset.json"), "ids[3]").unwrap_err();
            let message = error.to_string();
            assert!(message.contains("dataset.json") && message.contains("ids[3]"), "{message}");
        }
    }

    #[test]
    fn a_link_and_its_target_have_one_identity() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("cam00")).unwrap();
        std::os::unix::fs::symlink("cam00", dir.path().join("cam02")).unwrap();
        assert_eq!(FolderIdentity::of(&dir.path().join("cam02")), FolderIdentity::of(&dir.path().join("cam00")));
        assert_ne!(FolderIdentity::of(&dir.path().join("cam02")), FolderIdentity::of(dir.path()));
    }
}
