//! The corpus report rendered in headless Chromium, the labelled contact sheet, and the cog-nvs
//! export (`gt_rgb.mp4` + `train_render{k}.mp4`) decoding back to the stored frames.

use std::path::{Path, PathBuf};
use std::process::Command;

use datagen::pairs::generator::{PairsConfig, TrajectoryRequest, generate_clips};
use schemas::{ClipRecord, InputStatus, StatusRecord};

/// A shard of one synthetic clip of `frames` frames with `trajectories` sampled pairs, in `dir`.
fn shard(dir: &Path, frames: u32, trajectories: u32) -> (PathBuf, Vec<ClipRecord>) {
    let sequence = datagen::io::sequence::read_sequence(&crate::sequence::synth_sequence(dir, frames)).unwrap();
    let request = TrajectoryRequest { sampled: trajectories, explicit: Vec::new() };
    let records = generate_clips(&sequence, "synth", &PairsConfig::default(), &request, 4).unwrap();
    let (path, _) = datagen::pairs::generator::write_shard(
        &dir.join("corpus"),
        "synth",
        &records,
        schemas::InputDigest { source_path: "synth".into(), content_hash: String::new() },
    )
    .unwrap();
    (path, records)
}

#[test]
fn cog_nvs_export_decodes_to_the_stored_frames_under_the_public_names() {
    let dir = tempfile::tempdir().unwrap();
    let (path, records) = shard(dir.path(), 6, 2);
    let out = dir.path().join("cog-nvs");
    let folders = datagen::inspect::shards::export_cog_nvs(&path, &out).unwrap();
    assert_eq!(folders, vec![out.join(records[0].clip_id.replace('/', "__"))]);
    let mut names: Vec<String> = std::fs::read_dir(&folders[0])
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["gt_rgb.mp4", "meta.json", "train_render1.mp4", "train_render2.mp4"]);
    let record = &records[0];
    let decode = |bytes: &[u8]| image::load_from_memory(bytes).unwrap().to_rgb8();
    let targets: Vec<_> = record.frames.iter().map(|f| decode(f)).collect();
    // H.264 at CRF 17 on 64×48 synthetic frames: mean absolute error of a few levels.
    let mean_error = |a: &image::RgbImage, b: &image::RgbImage| {
        a.as_raw().iter().zip(b.as_raw()).map(|(&x, &y)| f64::from(x.abs_diff(y))).sum::<f64>()
            / a.as_raw().len() as f64
    };
    const MAX_MEAN_ERROR: f64 = 6.0;
    let gt = foundation::video::decode_video(&folders[0].join("gt_rgb.mp4")).unwrap();
    assert_eq!(gt.frames.len(), targets.len());
    assert!((gt.fps - record.fps).abs() < 1e-3, "{} fps, clip {}", gt.fps, record.fps);
    for (i, (a, b)) in gt.frames.iter().zip(&targets).enumerate() {
        assert!(mean_error(a, b) < MAX_MEAN_ERROR, "gt frame {i}: {}", mean_error(a, b));
    }
    for (k, trajectory) in record.trajectories.iter().enumerate() {
        let render = foundation::video::decode_video(&folders[0].join(format!("train_render{}.mp4", k + 1))).unwrap();
        assert_eq!(render.frames.len(), targets.len());
        for (i, frame) in render.frames.iter().enumerate() {
            let mask = image::load_from_memory(&trajectory.covisible_mask[i]).unwrap().to_luma8();
            let condition = image::RgbImage::from_fn(mask.width(), mask.height(), |x, y| {
                if mask.get_pixel(x, y).0[0] > 0 { *targets[i].get_pixel(x, y) } else { image::Rgb([0, 0, 0]) }
            });
            assert!(mean_error(frame, &condition) < MAX_MEAN_ERROR, "render {} frame {i}", k + 1);
        }
    }
    // The two conditioning videos differ: they are two trajectories' masks, in order.
    let first = foundation::video::decode_video(&folders[0].join("train_render1.mp4")).unwrap();
    let second = foundation::video::decode_video(&folders[0].join("train_render2.mp4")).unwrap();
    assert_ne!(first.frames, second.frames);
}

#[test]
fn exported_contact_sheets_have_a_header_and_frame_labels() {
    let dir = tempfile::tempdir().unwrap();
    let (path, records) = shard(dir.path(), 4, 1);
    let folders = datagen::inspect::shards::export(&path, &dir.path().join("export"), None).unwrap();
    let sheet = image::open(folders[0].join("contact_sheet.png")).unwrap().to_rgb8();
    let (width, height) = (records[0].width, records[0].height);
    let plain = foundation::contact_sheet::contact_sheet(&vec![vec![image::RgbImage::new(width, height); 3]; 4]);
    assert!(sheet.width() > plain.width() && sheet.height() > plain.height(), "room for header and labels");
    // Header text (light pixels) in the band above the first row.
    let header = image::imageops::crop_imm(&sheet, 0, 0, sheet.width(), sheet.height() - plain.height()).to_image();
    assert!(header.pixels().any(|p| p.0[0] > 200), "header drawn");
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(folders[0].join("meta.json")).unwrap()).unwrap();
    assert_eq!(meta["contact_sheet_columns"], serde_json::json!(["target", "co-visibility mask", "conditioning"]));
    assert_eq!(meta["contact_sheet_frames"], serde_json::json!([0, 1, 2, 3]));
}

/// The Chromium binary the report test renders with (installed by scripts/setup.sh).
const CHROMIUM: &str = "chromium";

#[test]
fn report_renders_in_headless_chromium_with_every_section() {
    let dir = tempfile::tempdir().unwrap();
    let (path, records) = shard(dir.path(), 4, 2);
    let corpus = path.parent().unwrap();
    // A status table with one ok and two failed inputs of the same kind.
    std::fs::create_dir_all(corpus.join("status")).unwrap();
    let row = |key: &str, status, reason: &str| StatusRecord {
        input_key: key.into(),
        status,
        reason: reason.into(),
        clips: 0,
        pairs: 0,
        shard: String::new(),
        content_hash: String::new(),
        seconds: 0.0,
        worker_index: 0,
        worker_count: 1,
    };
    let rows = [
        row("synth/synth", InputStatus::Ok, ""),
        row("sav/a", InputStatus::Failed, "/d/a.mp4: video: cannot open container"),
        row("sav/b", InputStatus::Failed, "/d/b.mp4: video: cannot open container"),
    ];
    schemas::write_status_table(&corpus.join("status/status-w000-000000.parquet"), &rows).unwrap();
    let export = dir.path().join("export");
    datagen::inspect::shards::export(&path, &export, None).unwrap();
    let out = dir.path().join("report/index.html");
    let options = datagen::inspect::report::ReportOptions { export_dir: Some(export.clone()), ..Default::default() };
    let summary = datagen::inspect::report::write_report(corpus, &out, &options).unwrap();
    assert_eq!((summary.clips, summary.pairs, summary.thumbnails, summary.failures), (1, 2, 1, 2));
    let html = std::fs::read_to_string(&out).unwrap();
    assert!(!html.contains("src=\"file:") && !html.contains("<link"), "self-contained: images are data URIs");
    assert!(html.contains(&format!(
        "{}/contact_sheet.png",
        datagen::inspect::shards::pair_id(&records[0], &records[0].trajectories[0])
    )));

    let profile = tempfile::tempdir().unwrap();
    let output = Command::new(CHROMIUM)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--enable-logging=stderr",
            "--v=0",
            "--virtual-time-budget=5000",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .arg("--dump-dom")
        .arg(format!("file://{}", std::path::absolute(&out).unwrap().display()))
        .output()
        .unwrap_or_else(|e| panic!("cannot run `{CHROMIUM}` (scripts/setup.sh installs it): {e}"));
    let dom = String::from_utf8_lossy(&output.stdout);
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "chromium failed: {log}");
    assert!(
        dom.contains("data-report-ready=\"ok\""),
        "the page's script ran and every image decoded:\n{dom:.2000}\n{log}"
    );
    assert!(dom.contains("ready: sections=totals,failures,histograms,thumbnails; images=1; broken=0"), "{dom:.3000}");
    assert!(!log.contains("Uncaught") && !log.contains(":ERROR:CONSOLE"), "console errors: {log}");
    for text in [
        "<h2>Totals</h2>",
        "1 ok, 0 skipped, 2 failed.",
        "<td>failed: video: cannot open container</td><td>2</td>",
        "co-visible fraction",
        "path length",
    ] {
        assert!(dom.contains(text), "`{text}` on the page");
    }
    assert!(dom.matches("<svg").count() >= 5, "one histogram per quantity");
}
