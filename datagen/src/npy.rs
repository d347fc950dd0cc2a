//! NumPy `.npy` arrays (and `.npz` members) in and out, through npyz: the reconstruction formats
//! of DESIGN §3 are NumPy files (`megasam_depth.npy`, `*_sgd_cvd_hr.npz`, ...).

use std::io::Read;
use std::path::Path;

use npyz::{DType, NpyFile, WriteOptions, WriterBuilder};

use crate::error::{Error, Result};

/// A dense n-dimensional array in C (row-major) order.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray<T> {
    /// Extent of each axis.
    pub shape: Vec<usize>,
    /// `shape.iter().product()` values, last axis fastest.
    pub data: Vec<T>,
}

impl<T> NdArray<T> {
    /// Fails with an error naming `path` and `field` unless the array has `expected.len()` axes
    /// and each axis given as `Some(n)` has extent `n`.
    pub fn expect_shape(&self, path: &Path, field: &str, expected: &[Option<usize>]) -> Result<()> {
        let matches = self.shape.len() == expected.len()
            && self.shape.iter().zip(expected).all(|(&got, want)| want.is_none_or(|w| w == got));
        if matches {
            return Ok(());
        }
        let want: Vec<String> = expected.iter().map(|e| e.map_or("_".to_owned(), |n| n.to_string())).collect();
        Err(Error::invalid(path, field, format!("expected shape ({}), found {:?}", want.join(", "), self.shape)))
    }
}

fn truncated(path: &Path, field: &str, error: std::io::Error) -> Error {
    Error::invalid(path, field, format!("cannot read array data (truncated or corrupt file?): {error}"))
}

/// Reads any real-valued array (float16/32/64, signed or unsigned integers, bool) as `f64`,
/// returning it in C order. `path` and `field` name the source in errors.
pub fn read_array_f64<R: Read>(npy: NpyFile<R>, path: &Path, field: &str) -> Result<NdArray<f64>> {
    if npy.order() == npyz::Order::Fortran {
        return Err(Error::invalid(
            path,
            field,
            "Fortran-ordered arrays are not supported; save with np.ascontiguousarray",
        ));
    }
    let shape: Vec<usize> = npy.shape().iter().map(|&n| n as usize).collect();
    let descr = match npy.dtype() {
        DType::Plain(type_str) => type_str.to_string(),
        other => return Err(Error::invalid(path, field, format!("unsupported dtype {}", other.descr()))),
    };
    let kind_and_size = descr.trim_start_matches(['<', '>', '|', '=']);
    let data: Vec<f64> = match kind_and_size {
        "f2" => npy.into_vec::<half::f16>().map(|v| v.into_iter().map(f64::from).collect()),
        "f4" => npy.into_vec::<f32>().map(|v| v.into_iter().map(f64::from).collect()),
        "f8" => npy.into_vec::<f64>(),
        "u1" => npy.into_vec::<u8>().map(|v| v.into_iter().map(f64::from).collect()),
        "b1" => npy.into_vec::<bool>().map(|v| v.into_iter().map(|b| f64::from(u8::from(b))).collect()),
        "i1" => npy.into_vec::<i8>().map(|v| v.into_iter().map(f64::from).collect()),
        "u2" => npy.into_vec::<u16>().map(|v| v.into_iter().map(f64::from).collect()),
        "i2" => npy.into_vec::<i16>().map(|v| v.into_iter().map(f64::from).collect()),
        "u4" => npy.into_vec::<u32>().map(|v| v.into_iter().map(f64::from).collect()),
        "i4" => npy.into_vec::<i32>().map(|v| v.into_iter().map(f64::from).collect()),
        "i8" => npy.into_vec::<i64>().map(|v| v.into_iter().map(|x| x as f64).collect()),
        "u8" => npy.into_vec::<u64>().map(|v| v.into_iter().map(|x| x as f64).collect()),
        _ => return Err(Error::invalid(path, field, format!("unsupported dtype `{descr}`"))),
    }
    .map_err(|e| truncated(path, field, e))?;
    let expected: usize = shape.iter().product();
    if data.len() != expected {
        return Err(Error::invalid(path, field, format!("holds {} values for shape {shape:?}", data.len())));
    }
    Ok(NdArray { shape, data })
}

/// Reads a `.npy` file as `f64` (see [`read_array_f64`]).
pub fn read_npy_f64(path: &Path) -> Result<NdArray<f64>> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let field = path.file_stem().unwrap_or_default().to_string_lossy().into_owned();
    let npy = NpyFile::new(std::io::BufReader::new(file))
        .map_err(|e| Error::invalid(path, &field, format!("not a valid .npy file: {e}")))?;
    read_array_f64(npy, path, &field)
}

/// Reads a `.npy` file as `f32` (values converted from any real dtype).
pub fn read_npy_f32(path: &Path) -> Result<NdArray<f32>> {
    let array = read_npy_f64(path)?;
    Ok(NdArray { shape: array.shape, data: array.data.into_iter().map(|v| v as f32).collect() })
}

/// Writes `data` with `shape` as a little-endian `.npy` file of `T`'s natural dtype.
pub fn write_npy<T: npyz::AutoSerialize>(path: &Path, shape: &[usize], data: &[T]) -> Result<()> {
    assert_eq!(shape.iter().product::<usize>(), data.len(), "shape and data disagree");
    let write = || -> std::io::Result<()> {
        let file = std::io::BufWriter::new(std::fs::File::create(path)?);
        let shape: Vec<u64> = shape.iter().map(|&n| n as u64).collect();
        let mut writer = WriteOptions::new().default_dtype().shape(&shape).writer(file).begin_nd()?;
        writer.extend(data.iter())?;
        writer.finish()
    };
    write().map_err(|e| Error::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f32_and_u8_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.npy");
        let data: Vec<f32> = (0..24).map(|i| i as f32 * 0.5 - 3.0).collect();
        write_npy(&path, &[2, 3, 4], &data).unwrap();
        let read = read_npy_f32(&path).unwrap();
        assert_eq!(read.shape, vec![2, 3, 4]);
        assert_eq!(read.data, data);
        let bytes: Vec<u8> = (0..6).collect();
        write_npy(&path, &[6], &bytes).unwrap();
        assert_eq!(read_npy_f64(&path).unwrap().data, vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    }

    #[test]
    fn truncated_file_names_file_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("megasam_depth.npy");
        write_npy(&path, &[100], &vec![1.0f32; 100]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 40]).unwrap();
        let error = read_npy_f32(&path).unwrap_err().to_string();
        assert!(error.contains("megasam_depth.npy") && error.contains("megasam_depth"), "{error}");
    }

    #[test]
    fn shape_check_reports_expected_and_found() {
        let array = NdArray { shape: vec![3, 4], data: vec![0.0; 12] };
        assert!(array.expect_shape("k.npy".as_ref(), "K", &[Some(3), Some(4)]).is_ok());
        let error = array.expect_shape("k.npy".as_ref(), "K", &[Some(3), Some(3)]).unwrap_err().to_string();
        assert!(error.contains("(3, 3)") && error.contains("[3, 4]"), "{error}");
    }
}
