//! A file written past the page cache (`O_DIRECT`) where the filesystem allows it, for shards:
//! tens of MB written once and synced at once. Through the page cache, `write` first copies every
//! byte into freshly allocated cache pages: on the 2-core benchmark machine that copy alone took
//! about 0.25 s of CPU for the 66 MB shard of `scripts/bench_pairs_vs.sh` (a profile of `datagen
//! pairs`), more than the rest of writing it, and the `fsync` that makes the shard durable then
//! writes those pages anyway. Direct writes go from the process's buffer to the device.
//!
//! Direct I/O needs the buffer's address, the write size and the file offset aligned to the
//! device's block size. The bytes are gathered in an aligned buffer of [`CHUNK`] bytes and written
//! a chunk at a time; the last, partial chunk is padded with zeros to a whole number of blocks,
//! written, and the file is cut back to its true length. Where the filesystem refuses `O_DIRECT`
//! (tmpfs before Linux 6.6, some network filesystems; at open or at the first write), the same
//! bytes go through ordinary buffered writes instead; the file's content is the same either way.

use std::fs::{File, OpenOptions};
use std::io::{self, Seek, SeekFrom, Write};
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};

/// Alignment of the buffer, of each write's size and of its file offset: 4 KiB covers the
/// logical block size of every common device (512 B or 4 KiB).
const BLOCK: usize = 4096;

/// Bytes gathered before each write: large enough that a shard takes a few dozen writes, small
/// against the memory of the process writing it.
pub const CHUNK: usize = 8 << 20;

/// A file being written from start to end, direct where possible (see the module documentation).
pub struct DirectFile {
    path: PathBuf,
    file: File,
    /// Whether `file` was opened with `O_DIRECT` (and has not fallen back since).
    direct: bool,
    /// [`CHUNK`] + [`BLOCK`] bytes, of which `CHUNK` from `start` on are block-aligned.
    buffer: Vec<u8>,
    start: usize,
    /// Bytes of the chunk gathered so far.
    filled: usize,
    /// Bytes written to the file before the current chunk (a multiple of [`CHUNK`]).
    written: u64,
}

impl DirectFile {
    /// Creates (or truncates) the file at `path`.
    pub fn create(path: &Path) -> io::Result<Self> {
        match Self::create_as(path, true) {
            Err(error) if error.raw_os_error() == Some(libc::EINVAL) => Self::create_as(path, false),
            result => result,
        }
    }

    /// Creates the file with or without `O_DIRECT`.
    fn create_as(path: &Path, direct: bool) -> io::Result<Self> {
        let mut options = OpenOptions::new();
        options.write(true).create(true).truncate(true);
        if direct {
            options.custom_flags(libc::O_DIRECT);
        }
        let file = options.open(path)?;
        let buffer = vec![0; CHUNK + BLOCK];
        // `align_offset` is at most BLOCK − 1 for a byte pointer; the vector is never resized, so
        // the aligned part stays where it is.
        let start = buffer.as_ptr().align_offset(BLOCK);
        assert!(start < BLOCK, "a byte buffer can always be aligned");
        Ok(Self { path: path.to_owned(), file, direct, buffer, start, filled: 0, written: 0 })
    }

    /// Writes the gathered chunk (`len` bytes of it, a multiple of [`BLOCK`] in direct mode) at
    /// the file's current position, falling back to buffered writes if the filesystem refuses
    /// the direct ones.
    fn write_chunk(&mut self, len: usize) -> io::Result<()> {
        let chunk = &self.buffer[self.start..self.start + len];
        if self.direct {
            match self.file.write_all(chunk) {
                Ok(()) => return Ok(()),
                Err(error) if error.raw_os_error() == Some(libc::EINVAL) => {
                    // Refused (the open accepted the flag, the filesystem not the I/O): reopen
                    // without it and write this chunk again where it starts.
                    let mut file = OpenOptions::new().write(true).open(&self.path)?;
                    file.seek(SeekFrom::Start(self.written))?;
                    self.file = file;
                    self.direct = false;
                }
                Err(error) => return Err(error),
            }
        }
        self.file.write_all(chunk)
    }

    /// Writes what is left, cuts the file to its length, syncs it to the device and gives its
    /// length. Nothing may be written after.
    pub fn complete(&mut self) -> io::Result<u64> {
        let tail = self.filled;
        let length = self.written + tail as u64;
        if self.direct {
            // Zero the padding (the buffer holds an earlier chunk's bytes there), write whole
            // blocks, and drop the padding from the file.
            let padded = tail.next_multiple_of(BLOCK);
            self.buffer[self.start + tail..self.start + padded].fill(0);
            self.write_chunk(padded)?;
            self.file.set_len(length)?;
        } else {
            self.write_chunk(tail)?;
        }
        self.file.sync_all()?;
        self.filled = 0;
        Ok(length)
    }
}

impl Write for DirectFile {
    fn write(&mut self, bytes: &[u8]) -> io::Result<usize> {
        let taken = bytes.len().min(CHUNK - self.filled);
        let at = self.start + self.filled;
        self.buffer[at..at + taken].copy_from_slice(&bytes[..taken]);
        self.filled += taken;
        if self.filled == CHUNK {
            self.write_chunk(CHUNK)?;
            self.written += CHUNK as u64;
            self.filled = 0;
        }
        Ok(taken)
    }

    /// Does nothing: a partial chunk can only be written once the file is complete
    /// ([`DirectFile::complete`]).
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bytes whose every position differs from its neighbours', so a misplaced chunk shows.
    fn pattern(len: usize) -> Vec<u8> {
        (0..len).map(|i| (i * 31 + i / 7919) as u8).collect()
    }

    #[test]
    fn any_length_written_in_any_pieces_reads_back_exactly() {
        let dir = tempfile::tempdir().unwrap();
        for len in [0, 1, BLOCK - 1, BLOCK, BLOCK + 1, CHUNK - 1, CHUNK, CHUNK + 5, 2 * CHUNK + 3 * BLOCK + 17] {
            let bytes = pattern(len);
            let path = dir.path().join(format!("f{len}"));
            let mut file = DirectFile::create(&path).unwrap();
            // Uneven pieces, some larger than a chunk.
            let mut rest = bytes.as_slice();
            for size in [3usize, 5000, CHUNK + 11].iter().cycle() {
                if rest.is_empty() {
                    break;
                }
                let (piece, tail) = rest.split_at((*size).min(rest.len()));
                file.write_all(piece).unwrap();
                rest = tail;
            }
            let written = file.complete().unwrap();
            assert_eq!(written, len as u64);
            assert!(std::fs::read(&path).unwrap() == bytes, "{len} bytes read back differently");
        }
    }

    #[test]
    fn buffered_writes_give_the_same_bytes() {
        // What a filesystem refusing O_DIRECT gets.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        let bytes = pattern(CHUNK + 3 * BLOCK + 1);
        let mut file = DirectFile::create_as(&path, false).unwrap();
        file.write_all(&bytes).unwrap();
        assert_eq!(file.complete().unwrap(), bytes.len() as u64);
        assert!(std::fs::read(&path).unwrap() == bytes);
    }

    #[test]
    fn creating_truncates_an_existing_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        std::fs::write(&path, pattern(3 * BLOCK)).unwrap();
        let mut file = DirectFile::create(&path).unwrap();
        file.write_all(b"short").unwrap();
        file.complete().unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"short");
    }
}
