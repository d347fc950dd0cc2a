//! TensorBoard event files written by `trainer::training::tensorboard` read back by the `tensorboard` package's own readers.

use std::path::Path;
use std::time::{SystemTime, UNIX_EPOCH};

use trainer::training::tensorboard::EventWriter;

use super::parity::run_python;

/// What `scripts/read_tensorboard.py` found in `dir` (strict CRC pass plus `EventAccumulator`).
fn read_back(dir: &Path) -> serde_json::Value {
    let out = dir.join("read_back.json");
    run_python("read_tensorboard.py", &[dir.join("events").as_os_str(), out.as_os_str()]);
    serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap()
}

/// (step, value, wall time) of scalar `tag`.
fn scalar_series(read: &serde_json::Value, tag: &str) -> Vec<(i64, f32, f64)> {
    let series = read["scalars"][tag].as_array().unwrap_or_else(|| panic!("no scalar tag {tag}: {read}"));
    series.iter().map(|e| (e[0].as_i64().unwrap(), e[1].as_f64().unwrap() as f32, e[2].as_f64().unwrap())).collect()
}

fn now() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).unwrap().as_secs_f64()
}

/// A small image whose every pixel differs, so a transposed or shifted decode shows.
fn test_image(width: u32, height: u32) -> image::RgbImage {
    image::RgbImage::from_fn(width, height, |x, y| {
        image::Rgb([(x * 37) as u8, (y * 53) as u8, (x * 11 + y * 7 + 5) as u8])
    })
}

#[test]
fn tensorboard_scalars_and_image_read_back_by_tensorboard() {
    let dir = tempfile::tempdir().unwrap();
    let start = now();
    let (width, height) = (11, 7);
    let image = test_image(width, height);
    // Values that are not round in binary, negative and tiny, to catch a wrong float width.
    let loss = |step: i64| 1.0f32 / (step as f32 + 0.3);
    let lr = |step: i64| -2e-5f32 * step as f32;
    let path = {
        let mut writer = EventWriter::create(&dir.path().join("events")).unwrap();
        for step in 1..=5 {
            writer.scalar("train/loss", step, loss(step)).unwrap();
            writer.scalars(step, &[("train/lr", lr(step)), ("train/step_seconds", 0.125)]).unwrap();
            if step == 3 {
                writer.image("validation/contact_sheet", step, &image).unwrap();
            }
        }
        writer.path().to_path_buf()
    };
    let end = now();
    let name = path.file_name().unwrap().to_str().unwrap();
    let parts: Vec<&str> = name.split('.').collect();
    assert_eq!(parts[..3], ["events", "out", "tfevents"], "file name {name}");
    let secs: u64 = parts[3].parse().unwrap_or_else(|_| panic!("file name {name}"));
    assert!((start as u64..=end as u64).contains(&secs), "file name {name}: time not in [{start}, {end}]");
    assert!(name.ends_with(&format!(".{}.0", std::process::id())), "file name {name}");

    let read = read_back(dir.path());
    let files = read["files"].as_array().unwrap();
    assert_eq!(files.len(), 1, "{read}");
    assert_eq!(files[0]["name"], name);
    assert_eq!(files[0]["file_version"], "brain.Event:2");
    // file_version + (loss, lr/step_seconds) per step + one image event.
    assert_eq!(files[0]["records"], 1 + 5 * 2 + 1);

    let mut tags: Vec<_> = read["scalars"].as_object().unwrap().keys().cloned().collect();
    tags.sort();
    assert_eq!(tags, ["train/loss", "train/lr", "train/step_seconds"]);
    for (tag, f) in
        [("train/loss", &loss as &dyn Fn(i64) -> f32), ("train/lr", &lr), ("train/step_seconds", &|_| 0.125)]
    {
        let series = scalar_series(&read, tag);
        assert_eq!(series.iter().map(|e| e.0).collect::<Vec<_>>(), [1, 2, 3, 4, 5], "{tag} steps");
        for (step, value, wall_time) in series {
            assert_eq!(value, f(step), "{tag} at step {step}");
            assert!(
                (start - 1.0..=end + 1.0).contains(&wall_time),
                "{tag} wall time {wall_time} not in [{start}, {end}]"
            );
        }
    }

    let images =
        read["images"]["validation/contact_sheet"].as_array().unwrap_or_else(|| panic!("no image tag: {read}"));
    assert_eq!(images.len(), 1);
    let decoded = &images[0];
    assert_eq!(decoded["step"], 3);
    assert_eq!(
        (decoded["width"].as_u64().unwrap(), decoded["height"].as_u64().unwrap()),
        (width.into(), height.into())
    );
    assert_eq!(decoded["format"], "PNG");
    assert_eq!(decoded["mode"], "RGB");
    assert_eq!(decoded["decoded_size"], serde_json::json!([width, height]));
    let pixels: Vec<u8> = (0..decoded["rgb_hex"].as_str().unwrap().len() / 2)
        .map(|i| u8::from_str_radix(&decoded["rgb_hex"].as_str().unwrap()[2 * i..2 * i + 2], 16).unwrap())
        .collect();
    assert_eq!(pixels, image.as_raw().as_slice(), "decoded pixels");
}

/// A run killed without a chance to flush (simulated by leaking the writer) keeps every step
/// before the last, and what is on disk is a valid event file.
#[test]
fn tensorboard_killed_run_loses_at_most_the_last_step() {
    let dir = tempfile::tempdir().unwrap();
    let mut writer = EventWriter::create(&dir.path().join("events")).unwrap();
    for step in 0..4 {
        writer.scalar("train/loss", step, step as f32 * 0.5).unwrap();
        writer.scalar("train/grad_norm", step, step as f32 * 2.0).unwrap();
    }
    std::mem::forget(writer);
    let read = read_back(dir.path());
    for (tag, scale) in [("train/loss", 0.5f32), ("train/grad_norm", 2.0)] {
        let series = scalar_series(&read, tag);
        let steps: Vec<_> = series.iter().map(|e| e.0).collect();
        assert!(steps.starts_with(&[0, 1, 2]), "{tag}: steps on disk {steps:?}");
        for (step, value, _) in series {
            assert_eq!(value, step as f32 * scale, "{tag} at step {step}");
        }
    }
}

/// Two writers opened in one folder in the same second by one process get distinct files.
#[test]
fn tensorboard_two_writers_get_distinct_files() {
    let dir = tempfile::tempdir().unwrap();
    let a = EventWriter::create(dir.path()).unwrap();
    let b = EventWriter::create(dir.path()).unwrap();
    assert_ne!(a.path(), b.path());
    assert!(a.path().exists() && b.path().exists());
}
