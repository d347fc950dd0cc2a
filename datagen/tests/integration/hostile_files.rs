//! Hostile array and raster files (lying EXR headers, npz bombs, corrupt or truncated members) fail with an error naming the file and member, never an abort or silent data.

use std::io::Write;
use std::path::Path;

use datagen::io::depth_exr::{decode_depth_exr, encode_depth_exr};
use datagen::io::sequence::{read_exr_folder, read_sequence};
use foundation::depth::DepthMap;

/// Frames, height and width of the small MegaSAM archive the npz cases start from.
const FRAMES: usize = 2;
const HEIGHT: usize = 4;
const WIDTH: usize = 6;

/// A `.npy` header (format 1.0) for `descr` and `shape`, padded as numpy pads it.
fn npy_header(descr: &str, shape: &[u64]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(u64::to_string).collect();
    let shape = if dims.len() == 1 { format!("({},)", dims[0]) } else { format!("({})", dims.join(", ")) };
    let mut text = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + text.len() + 1) % 64 != 0 {
        text.push(' ');
    }
    text.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(text.len() as u16).to_le_bytes());
    bytes.extend_from_slice(text.as_bytes());
    bytes
}

/// Both paths of the reader (little-endian floats a block of bytes at a time, other byte orders
/// through npyz) give the same values, across several blocks and a partial last one.
#[test]
fn npy_floats_of_either_byte_order_read_the_same_across_blocks() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("a.npy");
    let values: Vec<f64> = (0..150_001).map(|i| (i as f64 * 0.37).sin() * 1e3).collect();
    let f32s: Vec<f32> = values.iter().map(|&v| v as f32).collect();
    let as_f32: Vec<f64> = f32s.iter().map(|&v| f64::from(v)).collect();
    let cases: [(&str, Vec<u8>, &Vec<f64>); 4] = [
        ("<f8", values.iter().flat_map(|v| v.to_le_bytes()).collect(), &values),
        (">f8", values.iter().flat_map(|v| v.to_be_bytes()).collect(), &values),
        ("<f4", f32s.iter().flat_map(|v| v.to_le_bytes()).collect(), &as_f32),
        (">f4", f32s.iter().flat_map(|v| v.to_be_bytes()).collect(), &as_f32),
    ];
    for (descr, data, expected) in cases {
        let mut bytes = npy_header(descr, &[values.len() as u64]);
        bytes.extend_from_slice(&data);
        std::fs::write(&path, bytes).unwrap();
        let read = datagen::io::npy::read_npy_f64(&path).unwrap();
        assert_eq!((read.shape.as_slice(), &read.data), (&[values.len()][..], expected), "{descr}");
    }
}

fn npy_f32(shape: &[u64], values: &[f32]) -> Vec<u8> {
    let mut bytes = npy_header("<f4", shape);
    bytes.extend(values.iter().flat_map(|v| v.to_le_bytes()));
    bytes
}

fn npy_f64(shape: &[u64], values: &[f64]) -> Vec<u8> {
    let mut bytes = npy_header("<f8", shape);
    bytes.extend(values.iter().flat_map(|v| v.to_le_bytes()));
    bytes
}

/// One zip member as it goes into the file; the fields are public so tests can make them lie.
struct Member {
    name: String,
    /// 0 stored, 8 deflated.
    method: u16,
    /// The bytes in the file (compressed for method 8).
    payload: Vec<u8>,
    /// CRC-32 and uncompressed size as the directory records them.
    crc: u32,
    size: u32,
    /// Sizes in a zip64 extra field instead, with this uncompressed size (the fields say
    /// 0xFFFFFFFF, as zip64 writers do for members of 4 GiB and more).
    zip64: Option<u64>,
}

fn crc32(data: &[u8]) -> u32 {
    let mut crc = flate2::Crc::new();
    crc.update(data);
    crc.sum()
}

fn stored(name: &str, data: Vec<u8>) -> Member {
    Member { name: name.to_owned(), method: 0, crc: crc32(&data), size: data.len() as u32, payload: data, zip64: None }
}

fn deflated(name: &str, data: &[u8]) -> Member {
    let mut encoder = flate2::write::DeflateEncoder::new(Vec::new(), flate2::Compression::fast());
    encoder.write_all(data).unwrap();
    Member {
        name: name.to_owned(),
        method: 8,
        crc: crc32(data),
        size: data.len() as u32,
        payload: encoder.finish().unwrap(),
        zip64: None,
    }
}

/// A zip archive (no data descriptors; zip64 size fields where a member asks) of `members`, as
/// `np.savez` writes one.
fn zip(members: &[Member]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut directory = Vec::new();
    for member in members {
        let offset = out.len() as u32;
        // The zip64 extended information extra field: uncompressed, then compressed size.
        let mut extra = Vec::new();
        if let Some(size) = member.zip64 {
            extra.extend_from_slice(&1u16.to_le_bytes());
            extra.extend_from_slice(&16u16.to_le_bytes());
            extra.extend_from_slice(&size.to_le_bytes());
            extra.extend_from_slice(&(member.payload.len() as u64).to_le_bytes());
        }
        let common = |buf: &mut Vec<u8>| {
            let version = if member.zip64.is_some() { 45 } else { 20 };
            for half in [version, 0, member.method, 0, 0x21] {
                buf.extend_from_slice(&half.to_le_bytes());
            }
            let sizes = match member.zip64 {
                Some(_) => [u32::MAX, u32::MAX],
                None => [member.payload.len() as u32, member.size],
            };
            for word in [member.crc, sizes[0], sizes[1]] {
                buf.extend_from_slice(&word.to_le_bytes());
            }
            buf.extend_from_slice(&(member.name.len() as u16).to_le_bytes());
            buf.extend_from_slice(&(extra.len() as u16).to_le_bytes());
        };
        out.extend_from_slice(&0x0403_4b50u32.to_le_bytes());
        common(&mut out);
        out.extend_from_slice(member.name.as_bytes());
        out.extend_from_slice(&extra);
        out.extend_from_slice(&member.payload);

        directory.extend_from_slice(&0x0201_4b50u32.to_le_bytes());
        directory.extend_from_slice(&20u16.to_le_bytes());
        common(&mut directory);
        // Comment length, disk, internal and external attributes, local header offset.
        for half in [0u16, 0, 0] {
            directory.extend_from_slice(&half.to_le_bytes());
        }
        directory.extend_from_slice(&0u32.to_le_bytes());
        directory.extend_from_slice(&offset.to_le_bytes());
        directory.extend_from_slice(member.name.as_bytes());
        directory.extend_from_slice(&extra);
    }
    let directory_offset = out.len() as u32;
    out.extend_from_slice(&directory);
    out.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    for half in [0u16, 0, members.len() as u16, members.len() as u16] {
        out.extend_from_slice(&half.to_le_bytes());
    }
    out.extend_from_slice(&(directory.len() as u32).to_le_bytes());
    out.extend_from_slice(&directory_offset.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    out
}

/// The four members of a valid MegaSAM archive, `depths.npy` built by `depths`.
fn megasam_members(depths: impl FnOnce(Vec<u8>) -> Member) -> Vec<Member> {
    let mut images = npy_header("|u1", &[FRAMES as u64, HEIGHT as u64, WIDTH as u64, 3]);
    images.extend((0..FRAMES * HEIGHT * WIDTH * 3).map(|i| (i % 251) as u8));
    let depth: Vec<f32> = (0..FRAMES * HEIGHT * WIDTH).map(|i| 1.0 + i as f32 * 0.01).collect();
    let k = [100.0, 0.0, 2.5, 0.0, 100.0, 1.5, 0.0, 0.0, 1.0];
    let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
    let poses: Vec<f64> = (0..FRAMES).flat_map(|_| identity).collect();
    vec![
        stored("images.npy", images),
        depths(npy_f32(&[FRAMES as u64, HEIGHT as u64, WIDTH as u64], &depth)),
        stored("intrinsic.npy", npy_f64(&[3, 3], &k)),
        stored("cam_c2w.npy", npy_f64(&[FRAMES as u64, 4, 4], &poses)),
    ]
}

/// Writes `members` as the MegaSAM archive of a sequence folder under `dir`; returns the folder.
fn megasam_folder(dir: &Path, name: &str, members: &[Member]) -> std::path::PathBuf {
    let folder = dir.join(name);
    std::fs::create_dir_all(&folder).unwrap();
    std::fs::write(folder.join("scene_sgd_cvd_hr.npz"), zip(members)).unwrap();
    folder
}

fn error_of(folder: &Path) -> String {
    match read_sequence(folder) {
        Ok(_) => panic!("{} must fail", folder.display()),
        Err(error) => error.to_string(),
    }
}

fn assert_names(error: &str, needles: &[&str]) {
    for needle in needles {
        assert!(error.contains(needle), "`{error}` should contain `{needle}`");
    }
}

#[test]
fn hand_built_archives_read_stored_and_deflated() {
    // The control for every npz case below: the same archive, unbroken, reads.
    let dir = tempfile::tempdir().unwrap();
    let stored_folder = megasam_folder(dir.path(), "stored", &megasam_members(|d| stored("depths.npy", d)));
    let deflated_folder = megasam_folder(dir.path(), "deflated", &megasam_members(|d| deflated("depths.npy", &d)));
    for folder in [stored_folder, deflated_folder] {
        let sequence = read_sequence(&folder).unwrap();
        assert_eq!((sequence.len(), sequence.size()), (FRAMES, (WIDTH as u32, HEIGHT as u32)));
        assert_eq!(sequence.depth[1].values[0], 1.0 + (HEIGHT * WIDTH) as f32 * 0.01);
    }
}

#[test]
fn npz_member_declaring_a_huge_shape_fails_before_it_is_inflated() {
    let dir = tempfile::tempdir().unwrap();
    // A deflated member of zeros whose header claims 2×100000×100000 float32 (80 GB), and whose
    // directory entry claims as much as its deflate stream could inflate to (1000×).
    let members = megasam_members(|_| {
        let mut data = npy_header("<f4", &[FRAMES as u64, 100_000, 100_000]);
        data.resize(data.len() + (1 << 20), 0);
        let member = deflated("depths.npy", &data);
        Member { size: member.payload.len() as u32 * 1000, ..member }
    });
    let error = error_of(&megasam_folder(dir.path(), "huge", &members));
    assert_names(&error, &["scene_sgd_cvd_hr.npz", "member `depths.npy`", "100000"]);
}

#[test]
fn npz_member_mismatching_its_siblings_fails_naming_both_shapes() {
    let dir = tempfile::tempdir().unwrap();
    // A consistent member (header, directory and data agree) with 3 frames where images has 2.
    let members = megasam_members(|_| {
        let depth = vec![1.0f32; 3 * HEIGHT * WIDTH];
        deflated("depths.npy", &npy_f32(&[3, HEIGHT as u64, WIDTH as u64], &depth))
    });
    let error = error_of(&megasam_folder(dir.path(), "siblings", &members));
    assert_names(&error, &["scene_sgd_cvd_hr.npz", "member `depths.npy`", "[3, 4, 6]", "(2, "]);
}

#[test]
fn npz_member_inflating_beyond_its_directory_size_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    // The directory gives the member its array's size; the deflate stream holds 64 MiB more.
    let members = megasam_members(|depths| {
        let declared = depths.len() as u32;
        let mut bomb = depths;
        bomb.resize(bomb.len() + (64 << 20), 0);
        let crc = crc32(&bomb[..declared as usize]);
        Member { size: declared, crc, ..deflated("depths.npy", &bomb) }
    });
    let error = error_of(&megasam_folder(dir.path(), "bomb", &members));
    assert_names(&error, &["scene_sgd_cvd_hr.npz", "member `depths.npy`", "inflates beyond"]);
}

#[test]
fn npz_member_with_lying_sizes_within_the_ceilings_does_not_allocate_them() {
    let dir = tempfile::tempdir().unwrap();
    // Header and directory agree on 2×16384×16384 float32 (2 GiB); only 1 KiB of data exists.
    let members = megasam_members(|_| {
        let mut data = npy_header("<f4", &[FRAMES as u64, 16_384, 16_384]);
        let declared = data.len() as u32 + 2 * 16_384 * 16_384 * 4;
        data.resize(data.len() + 1024, 0);
        Member { size: declared, ..deflated("depths.npy", &data) }
    });
    let error = error_of(&megasam_folder(dir.path(), "lying", &members));
    assert_names(&error, &["scene_sgd_cvd_hr.npz", "member `depths.npy`"]);
}

#[test]
fn corrupted_stored_npz_member_is_a_crc_mismatch() {
    let dir = tempfile::tempdir().unwrap();
    let members = megasam_members(|depths| {
        let mut member = stored("depths.npy", depths);
        // Flip one bit of the last value, keeping the header and the directory's CRC.
        let last = member.payload.len() - 2;
        member.payload[last] ^= 0x10;
        member
    });
    let error = error_of(&megasam_folder(dir.path(), "corrupt", &members));
    assert_names(&error, &["scene_sgd_cvd_hr.npz", "member `depths.npy`", "CRC mismatch"]);
}

#[test]
fn missing_npz_member_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let mut members = megasam_members(|d| stored("depths.npy", d));
    members.remove(3);
    let error = error_of(&megasam_folder(dir.path(), "missing", &members));
    assert_names(&error, &["scene_sgd_cvd_hr.npz", "member `cam_c2w.npy`", "missing"]);
}

#[test]
fn truncated_npy_names_the_file_not_a_field_from_its_stem() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("megasam_depth.npy");
    let bytes = npy_f32(&[3, 48, 64], &vec![1.0; 3 * 48 * 64]);
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let error = datagen::io::npy::read_npy_f64(&path).unwrap_err().to_string();
    assert_names(&error, &["megasam_depth.npy: ", "truncated", "[3, 48, 64]"]);
    assert!(!error.contains("field `megasam_depth`"), "{error}");
}

#[test]
fn npy_header_claiming_gigabytes_fails_without_allocating_them() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bomb.npy");
    // 2^40 values in a 128-byte file, and a format 2.0 header that claims 4 GiB of text.
    std::fs::write(&path, npy_header("<f8", &[1 << 20, 1 << 20])).unwrap();
    let error = datagen::io::npy::read_npy_f64(&path).unwrap_err().to_string();
    assert_names(&error, &["bomb.npy", "1048576"]);
    let mut long_text = b"\x93NUMPY\x02\x00".to_vec();
    long_text.extend_from_slice(&u32::MAX.to_le_bytes());
    std::fs::write(&path, long_text).unwrap();
    let error = datagen::io::npy::read_npy_f64(&path).unwrap_err().to_string();
    assert_names(&error, &["bomb.npy", "header"]);
    // An empty array whose other extents overflow every product of them.
    std::fs::write(&path, npy_header("<f4", &[1 << 40, 1 << 40, 0])).unwrap();
    let error = datagen::io::npy::read_npy_f64(&path).unwrap_err().to_string();
    assert_names(&error, &["bomb.npy", "1099511627776"]);
}

/// A small valid depth EXR whose `dataWindow` is rewritten to `width × height`.
fn exr_declaring(width: i32, height: i32) -> Vec<u8> {
    let depth = DepthMap { width: 8, height: 4, values: vec![2.0; 32] };
    let mut bytes = encode_depth_exr(&depth).unwrap();
    let name = b"dataWindow\0box2i\0";
    let at = bytes.windows(name.len()).position(|w| w == name).unwrap() + name.len() + 4;
    bytes[at + 8..at + 12].copy_from_slice(&(width - 1).to_le_bytes());
    bytes[at + 12..at + 16].copy_from_slice(&(height - 1).to_le_bytes());
    // Room for the offset table such a window needs, so that only the size itself can stop it.
    bytes.resize(bytes.len() + (height as usize).div_ceil(16) * 8, 0);
    bytes
}

#[test]
fn exr_declaring_a_huge_data_window_fails_naming_the_field() {
    let error = decode_depth_exr(&exr_declaring(100_000, 100_000), "depth/00000.exr").unwrap_err().to_string();
    assert_names(&error, &["depth/00000.exr", "dataWindow", "100000x100000"]);

    // In a folder: the file is named, and the maps are compared before any is decoded.
    let dir = tempfile::tempdir().unwrap();
    let depth = DepthMap { width: 8, height: 4, values: vec![2.0; 32] };
    std::fs::write(dir.path().join("00000.exr"), encode_depth_exr(&depth).unwrap()).unwrap();
    std::fs::write(dir.path().join("00001.exr"), exr_declaring(100_000, 100_000)).unwrap();
    let error = read_exr_folder(dir.path()).unwrap_err().to_string();
    assert_names(&error, &["00001.exr", "dataWindow"]);
    std::fs::write(dir.path().join("00001.exr"), exr_declaring(16, 4)).unwrap();
    let error = read_exr_folder(dir.path()).unwrap_err().to_string();
    assert_names(&error, &["00001.exr", "16x4", "8x4"]);
}

#[test]
fn npz_member_whose_zip64_directory_claims_gigabytes_for_kilobytes_is_a_lie_named() {
    let dir = tempfile::tempdir().unwrap();
    // Header and zip64 directory agree on 2×16384×16384 float32 (2 GiB); the member deflates
    // 1 KiB of zeros, which no deflate stream of its size can inflate to.
    let members = megasam_members(|_| {
        let mut data = npy_header("<f4", &[FRAMES as u64, 16_384, 16_384]);
        let declared = data.len() as u64 + 2 * 16_384 * 16_384 * 4;
        data.resize(data.len() + 1024, 0);
        Member { zip64: Some(declared), ..deflated("depths.npy", &data) }
    });
    let error = error_of(&megasam_folder(dir.path(), "zip64", &members));
    assert_names(&error, &["scene_sgd_cvd_hr.npz", "member `depths.npy`", "compressed bytes", "lies"]);
    // A stored member is its bytes: declaring more is the same lie.
    let members = megasam_members(|depths| {
        let size = depths.len() as u32 + 4096;
        Member { size, ..stored("depths.npy", depths) }
    });
    let error = error_of(&megasam_folder(dir.path(), "stored", &members));
    assert_names(&error, &["scene_sgd_cvd_hr.npz", "member `depths.npy`", "stored member", "lies"]);
}

/// A ViPE folder of the tool_layouts scene, whose depth zip is then replaced by `members`.
fn vipe_with_depth(dir: &Path, members: impl FnOnce(Vec<Vec<u8>>) -> Vec<Member>) -> std::path::PathBuf {
    let truth = super::tool_layouts::Truth::new(2);
    let root = super::tool_layouts::write_vipe(&truth, &dir.join("vipe"), "clip");
    let zip_path = root.join("depth/clip.zip");
    let mut archive = zip::ZipArchive::new(std::fs::File::open(&zip_path).unwrap()).unwrap();
    let maps: Vec<Vec<u8>> = (0..archive.len())
        .map(|i| {
            let mut bytes = Vec::new();
            std::io::Read::read_to_end(&mut archive.by_index(i).unwrap(), &mut bytes).unwrap();
            bytes
        })
        .collect();
    std::fs::write(&zip_path, zip(&members(maps))).unwrap();
    root
}

#[test]
fn vipe_depth_member_inflating_beyond_its_declared_size_stops_there() {
    let dir = tempfile::tempdir().unwrap();
    // Frame 1's member declares its EXR's size, but its deflate stream goes on for 64 MiB.
    let root = vipe_with_depth(dir.path(), |maps| {
        let declared = maps[1].len();
        let mut bomb = maps[1].clone();
        bomb.resize(declared + (64 << 20), 0);
        let crc = crc32(&bomb[..declared]);
        vec![deflated("00000.exr", &maps[0]), Member { size: declared as u32, crc, ..deflated("00001.exr", &bomb) }]
    });
    let error = error_of(&root);
    assert_names(&error, &["depth/clip.zip", "member `00001.exr`", "inflates beyond"]);
    // The control: the same members, honest, read.
    let root = vipe_with_depth(&dir.path().join("honest"), |maps| {
        vec![deflated("00000.exr", &maps[0]), deflated("00001.exr", &maps[1])]
    });
    read_sequence(&root).unwrap();
}

#[test]
fn vipe_errors_use_vipe_field_names() {
    let dir = tempfile::tempdir().unwrap();
    let truth = super::tool_layouts::Truth::new(2);
    let root = super::tool_layouts::write_vipe(&truth, &dir.path().join("vipe"), "clip");
    // Pose 1 scaled: not rigid. The error names ViPE's array and index, not the toolkit's.
    let mut poses: Vec<f64> = truth.world_from_camera.iter().flat_map(foundation::camera::mat4_to_row_major).collect();
    for (row, col) in (0..3).flat_map(|row| (0..3).map(move |col| (row, col))) {
        poses[16 + row * 4 + col] *= 2.0;
    }
    super::tool_layouts::write_npz(
        &root.join("pose/clip.npz"),
        vec![
            ("data", vec![2, 4, 4], super::tool_layouts::Values::F64(&poses)),
            ("inds", vec![2], super::tool_layouts::Values::I64(vec![0, 1])),
        ],
    );
    let error = error_of(&root);
    assert_names(&error, &["pose/clip.npz", "data[1]"]);
    assert!(!error.contains("world_from_camera"), "{error}");
}

#[test]
fn gen3c_mask_with_nan_values_is_refused_like_depth() {
    let dir = tempfile::tempdir().unwrap();
    let truth = super::tool_layouts::Truth::new(2);
    let root = super::tool_layouts::write_gen3c(&truth, &dir.path().join("gen3c"));
    read_sequence(&root).unwrap();
    let (h, w) = (truth.height as u64, truth.width as u64);
    let mut mask = vec![1.0f32; (2 * h * w) as usize];
    mask[(h * w) as usize + 5] = f32::NAN;
    super::tool_layouts::write_npz(
        &root.join("mask.npz"),
        vec![("mask", vec![2, h, w], super::tool_layouts::Values::F32(mask))],
    );
    let error = error_of(&root);
    assert_names(&error, &["mask.npz", "member `mask.npy`", "frame 1", "pixel (5, 0)", "NaN"]);
}
