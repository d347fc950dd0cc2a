//! The one layout registry: every command that reads a folder takes the same `--layout` names,
//! and a single-camera read of a multi-camera scene takes its input camera or is refused.

use std::path::Path;

use clap::Parser;
use datagen::cli::{Cli, Command};
use datagen::io::layout::{
    FolderLayout, Layout, LayoutName, MultiViewLayoutName, ReadOptions, folder_layout, read_camera_sequence,
    read_multiview_as,
};
use datagen::synth::{CameraRig, SynthConfig, write_multiview};
use datagen::synth_layouts::{write_dycheck, write_kubric4d};

/// Three cameras: too few for Kubric-4D's input view 4, so that scene has no input camera.
const RIG: CameraRig = CameraRig { cameras: 3, spacing_deg: 8.0 };

fn config() -> SynthConfig {
    SynthConfig { width: 32, height: 24, frames: 2, ..SynthConfig::default() }
}

/// The layout each folder-reading command parsed from `--layout NAME`.
fn parsed_layouts(name: &str) -> Vec<Option<LayoutName>> {
    let commands: [&[&str]; 6] = [
        &["pairs", "seq", "--out", "o"],
        &["render", "seq", "--trajectory", "t.npy", "--out", "o"],
        &["check", "seq"],
        &["view", "seq", "--out", "o.rrd"],
        &["build", "--config", "c.toml"],
        &["trajectories", "collect", "seq", "--out", "b.parquet"],
    ];
    commands
        .iter()
        .map(|args| {
            let argv: Vec<&str> =
                ["datagen"].into_iter().chain(args.iter().copied()).chain(["--layout", name]).collect();
            match Cli::try_parse_from(argv).unwrap_or_else(|e| panic!("{args:?} --layout {name}: {e}")).command {
                Command::Pairs(a) => a.read.layout,
                Command::Render(a) => a.read.layout,
                Command::Check(a) => a.read.layout,
                Command::View(a) => a.read.layout,
                Command::Build(a) => a.layout,
                Command::Trajectories { command: datagen::cli::trajectories::TrajectoriesCommand::Collect(a) } => {
                    a.layout
                }
                other => panic!("unexpected command {other:?}"),
            }
        })
        .collect()
}

#[test]
fn every_folder_command_takes_every_layout_name() {
    for name in LayoutName::ALL {
        assert_eq!(parsed_layouts(name.as_str()), vec![Some(name); 6], "{name}");
    }
    let names: Vec<&str> = LayoutName::ALL.iter().map(|n| n.as_str()).collect();
    assert_eq!(
        names,
        [
            "cog-nvs",
            "megasam",
            "generic",
            "vipe",
            "vggt",
            "colmap",
            "gen3c",
            "depth-only",
            "dycheck",
            "kubric4d",
            "pardom4d"
        ]
    );
    let error =
        Cli::try_parse_from(["datagen", "render", "seq", "--trajectory", "t", "--out", "o", "--layout", "nope"])
            .unwrap_err()
            .to_string();
    assert!(error.contains("unknown layout `nope`") && error.contains("depth-only, dycheck"), "{error}");
    // The scene names convert both ways: the trainer's `MultiViewLayoutName` is part of the set.
    for scene in MultiViewLayoutName::ALL {
        assert_eq!(LayoutName::from(scene).multiview(), Some(scene));
        assert_eq!(scene.as_str().parse::<LayoutName>().unwrap(), LayoutName::from(scene));
    }
}

#[test]
fn a_single_camera_read_of_a_scene_takes_its_input_camera() {
    let dir = tempfile::tempdir().unwrap();
    let dycheck = write_dycheck(&config(), &RIG, &dir.path().join("dy"), |_| {}).unwrap();
    let (sequence, layout) =
        read_camera_sequence(&dycheck, Some(LayoutName::Dycheck), &ReadOptions::default()).unwrap();
    assert_eq!(layout, FolderLayout::Scene(MultiViewLayoutName::Dycheck));
    let scene = read_multiview_as(&dycheck, None).unwrap();
    let input = scene.camera(&scene.split.as_ref().unwrap().input).unwrap();
    assert_eq!(sequence.frames, input.sequence.frames);
    assert_eq!(sequence.cameras, input.sequence.cameras);
    assert_eq!(sequence.depth, input.sequence.depth);
    // Undetected, a scene is no sequence folder: single-camera commands detect sequences only.
    let text = read_camera_sequence(&dycheck, None, &ReadOptions::default()).unwrap_err().to_string();
    assert!(text.contains("not a sequence folder"), "{text}");

    // Scenes without an input camera are refused naming the folder and the layout.
    let refused = |path: &Path, name: LayoutName| {
        let text = read_camera_sequence(path, Some(name), &ReadOptions::default()).unwrap_err().to_string();
        assert!(text.contains(&path.display().to_string()) && text.contains(name.as_str()), "{text}");
        assert!(text.contains("no input camera"), "{text}");
    };
    let kubric = write_kubric4d(&config(), &RIG, &dir.path().join("scn00001"), |_| {}).unwrap();
    refused(&kubric, LayoutName::Kubric4d);
    let rig = write_multiview(&config(), &RIG, &dir.path().join("rig"), |_| {}).unwrap();
    refused(&rig, LayoutName::Generic);

    // `datagen check --layout dycheck` checks the input camera under the scene's conventions.
    let args = datagen::cli::check::CheckArgs {
        seq_dir: dycheck,
        read: datagen::cli::flags::ReadArgs { layout: Some(LayoutName::Dycheck), vggt_conf_percentile: None },
        json: true,
        config: None,
    };
    let report = args.report().unwrap();
    assert_eq!(report.layout, "dycheck");
    assert!(report.conventions.contains("camera_from_world"), "{}", report.conventions);
}

#[test]
fn generic_names_a_sequence_or_a_scene_by_the_files() {
    let dir = tempfile::tempdir().unwrap();
    let rig = write_multiview(&config(), &RIG, &dir.path().join("rig"), |_| {}).unwrap();
    let camera = rig.join("cam00");
    assert_eq!(
        folder_layout(&rig, Some(LayoutName::Generic)).unwrap(),
        FolderLayout::Scene(MultiViewLayoutName::Generic)
    );
    assert_eq!(folder_layout(&rig, None).unwrap(), FolderLayout::Scene(MultiViewLayoutName::Generic));
    assert_eq!(folder_layout(&camera, Some(LayoutName::Generic)).unwrap(), FolderLayout::Sequence(Layout::Generic));
    assert_eq!(folder_layout(&camera, None).unwrap(), FolderLayout::Sequence(Layout::Generic));
    // A scene layout named for a sequence folder is the scene's reader's to refuse.
    assert_eq!(
        folder_layout(&camera, Some(LayoutName::Dycheck)).unwrap(),
        FolderLayout::Scene(MultiViewLayoutName::Dycheck)
    );
    assert!(read_camera_sequence(&camera, Some(LayoutName::Dycheck), &ReadOptions::default()).is_err());
    // The old single-camera entry refuses a scene layout naming it.
    let text = datagen::io::sequence::read_sequence_as(&camera, Some(LayoutName::Kubric4d)).unwrap_err().to_string();
    assert!(text.contains("kubric4d is a multi-camera layout"), "{text}");
}

#[test]
fn a_corpus_config_names_its_layout() {
    #[derive(serde::Deserialize)]
    struct Key {
        layout: LayoutName,
    }
    let key: Key = toml::from_str("layout = \"vipe\"").unwrap();
    assert_eq!(key.layout, LayoutName::Vipe);
    let error = toml::from_str::<Key>("layout = \"mp4\"").err().unwrap().to_string();
    assert!(error.contains("unknown layout `mp4`"), "{error}");
}
