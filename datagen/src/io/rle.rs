//! COCO run-length encoded masks, as SA-V stores its masklets (`{"size": [H, W], "counts": str}`):
//! runs alternate background/foreground starting with background, over pixels in column-major
//! (Fortran) order; the compressed string packs each run length (as a difference to the run two
//! back, from the third run on) into 5-bit groups, low group first, offset by ASCII 48, with bit
//! 0x20 marking "more groups follow" and bit 0x10 of the last group the sign.

use serde::Deserialize;

/// An RLE mask as stored in COCO/SA-V JSON: either compressed (string) or plain (list of runs).
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct CocoRle {
    /// `[height, width]`.
    pub size: [usize; 2],
    /// Run lengths.
    pub counts: RleCounts,
}

/// The two encodings of `counts`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(untagged)]
pub enum RleCounts {
    /// pycocotools' compressed string.
    Compressed(String),
    /// Plain run lengths.
    Runs(Vec<u64>),
}

/// Why an RLE could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RleError {
    /// A character outside the encoding's alphabet, or a string ending mid-number.
    #[error("malformed compressed counts at character {0}")]
    Malformed(usize),
    /// A negative run length after delta decoding.
    #[error("negative run length at run {0}")]
    NegativeRun(usize),
    /// Runs that do not add up to height × width.
    #[error("runs cover {covered} pixels, mask has {expected}")]
    WrongTotal {
        /// Pixels covered by the runs.
        covered: u64,
        /// height × width.
        expected: u64,
    },
}

/// Decodes pycocotools' compressed counts string into run lengths.
pub fn decode_counts(text: &str) -> Result<Vec<u64>, RleError> {
    let bytes = text.as_bytes();
    let mut runs: Vec<i64> = Vec::new();
    let mut position = 0;
    while position < bytes.len() {
        let mut value: i64 = 0;
        let mut shift = 0;
        loop {
            let byte = *bytes.get(position).ok_or(RleError::Malformed(position))?;
            let group = i64::from(byte.checked_sub(48).filter(|g| *g < 64).ok_or(RleError::Malformed(position))?);
            position += 1;
            if shift >= 60 {
                return Err(RleError::Malformed(position));
            }
            value |= (group & 0x1f) << shift;
            shift += 5;
            if group & 0x20 == 0 {
                if group & 0x10 != 0 {
                    value |= -1i64 << shift;
                }
                break;
            }
        }
        if runs.len() > 2 {
            value += runs[runs.len() - 2];
        }
        if value < 0 {
            return Err(RleError::NegativeRun(runs.len()));
        }
        runs.push(value);
    }
    Ok(runs.into_iter().map(|r| r as u64).collect())
}

/// Encodes run lengths as pycocotools' compressed counts string (the inverse of
/// [`decode_counts`]).
pub fn encode_counts(runs: &[u64]) -> String {
    let mut text = String::new();
    for (i, &run) in runs.iter().enumerate() {
        let mut value = run as i64;
        if i > 2 {
            value -= runs[i - 2] as i64;
        }
        loop {
            let mut group = (value & 0x1f) as u8;
            value >>= 5;
            let more = if group & 0x10 != 0 { value != -1 } else { value != 0 };
            if more {
                group |= 0x20;
            }
            text.push(char::from(group + 48));
            if !more {
                break;
            }
        }
    }
    text
}

/// Run lengths of a row-major mask in COCO's column-major order, starting with background.
pub fn mask_runs(mask: &[bool], height: usize, width: usize) -> Vec<u64> {
    let mut runs = vec![0u64];
    let mut current = false;
    for column in 0..width {
        for row in 0..height {
            let on = mask[row * width + column];
            if on != current {
                runs.push(0);
                current = on;
            }
            *runs.last_mut().expect("starts with one run") += 1;
        }
    }
    runs
}

impl CocoRle {
    /// Decodes to a row-major mask of `height * width` booleans.
    pub fn decode(&self) -> Result<Vec<bool>, RleError> {
        let [height, width] = self.size;
        let runs = match &self.counts {
            RleCounts::Compressed(text) => decode_counts(text)?,
            RleCounts::Runs(runs) => runs.clone(),
        };
        let expected = (height * width) as u64;
        let covered: u64 = runs.iter().sum();
        if covered != expected {
            return Err(RleError::WrongTotal { covered, expected });
        }
        let mut mask = vec![false; height * width];
        let mut index = 0usize;
        for (run, &length) in runs.iter().enumerate() {
            if run % 2 == 1 {
                for i in index..index + length as usize {
                    // Column-major index i → (row, column).
                    let (column, row) = (i / height, i % height);
                    mask[row * width + column] = true;
                }
            }
            index += length as usize;
        }
        Ok(mask)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encode_inverts_decode() {
        let mask: Vec<bool> = (0..12 * 7).map(|i| (i * 7919 % 13) < 5).collect();
        let runs = mask_runs(&mask, 7, 12);
        let text = encode_counts(&runs);
        assert_eq!(decode_counts(&text).unwrap(), runs);
        let rle = CocoRle { size: [7, 12], counts: RleCounts::Compressed(text) };
        assert_eq!(rle.decode().unwrap(), mask);
        // Large runs and negative deltas.
        let runs = vec![100_000, 3, 2, 70_000, 1, 1];
        assert_eq!(decode_counts(&encode_counts(&runs)).unwrap(), runs);
    }

    /// Encodes runs the way pycocotools does (the inverse of `decode_counts`), for tests.
    fn encode_counts(runs: &[u64]) -> String {
        let mut out = String::new();
        for (i, &run) in runs.iter().enumerate() {
            let mut value = run as i64 - if i > 2 { runs[i - 2] as i64 } else { 0 };
            loop {
                let mut group = value & 0x1f;
                value >>= 5;
                let more = if group & 0x10 != 0 { value != -1 } else { value != 0 };
                if more {
                    group |= 0x20;
                }
                out.push((group as u8 + 48) as char);
                if !more {
                    break;
                }
            }
        }
        out
    }

    #[test]
    fn decodes_a_known_column_major_mask() {
        // 3×4 mask, column-major runs: 2 off, 3 on, 4 off, 3 on.
        let rle = CocoRle { size: [3, 4], counts: RleCounts::Runs(vec![2, 3, 4, 3]) };
        let mask = rle.decode().unwrap();
        let rows: Vec<String> =
            mask.chunks(4).map(|r| r.iter().map(|&b| if b { '#' } else { '.' }).collect()).collect();
        assert_eq!(rows, vec![".#.#", ".#.#", "#..#"]);
    }

    #[test]
    fn compressed_counts_round_trip_including_large_and_decreasing_runs() {
        let runs = vec![0, 5, 1000, 3, 70_000, 2, 1, 1_000_000, 17];
        assert_eq!(decode_counts(&encode_counts(&runs)).unwrap(), runs);
    }

    #[test]
    fn small_runs_are_single_characters_and_deltas_start_at_the_fourth_run() {
        // Values below 16 encode as one character, value + 48; the fourth run is stored as the
        // difference to the second: runs [5, 2, 7, 4] → '5', '2', '7', 4 − 2 = 2 → '2'.
        assert_eq!(decode_counts("5272").unwrap(), vec![5, 2, 7, 4]);
        let rle = CocoRle { size: [6, 3], counts: RleCounts::Compressed("5272".into()) };
        assert_eq!(rle.decode().unwrap().iter().filter(|&&b| b).count(), 6);
    }

    #[test]
    fn corrupt_counts_are_errors() {
        assert!(matches!(decode_counts("5\u{7f}"), Err(RleError::Malformed(1))));
        assert!(
            matches!(decode_counts("o"), Err(RleError::Malformed(1))),
            "0x3f has the 'more' bit and nothing follows"
        );
        let short = CocoRle { size: [4, 4], counts: RleCounts::Runs(vec![3, 2]) };
        assert_eq!(short.decode(), Err(RleError::WrongTotal { covered: 5, expected: 16 }));
    }
}
