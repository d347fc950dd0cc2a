//! The shard data loader: batch shapes and values, determinism per seed, exact resume from a
//! stored position, disjoint and complete rank partitions, named errors for bad shard folders,
//! and a fixed share of multi-view pairs per batch that does not depend on the world size.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use trainer::tch::Kind;
use trainer::training::data::{DataConfig, DataPosition, ShardLoader};

/// Two shards of synthetic pairs: 3 videos × 2 clips, 2 trajectories each (generated once).
fn shards() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let pairs = datagen::pairs::generator::PairsConfig {
            clip: datagen::pairs::clip::ClipConfig { length: 5, stride: 4, max_clips: 0 },
            ..Default::default()
        };
        let request = datagen::pairs::generator::TrajectoryRequest { sampled: 2, explicit: Vec::new() };
        for seed in 0..3u64 {
            let scene = datagen::synth::SynthConfig { width: 48, height: 32, frames: 9, seed, ..Default::default() };
            let seq = dir.path().join(format!("seq{seed}"));
            datagen::synth::write_sequence(&scene, &seq, |_| {}).unwrap();
            let sequence = datagen::io::sequence::read_sequence(&seq).unwrap();
            let records =
                datagen::pairs::generator::generate_clips(&sequence, "synth", &pairs, &request, seed).unwrap();
            let digest = schemas::InputDigest { source_path: seq.display().to_string(), content_hash: String::new() };
            let shard = if seed < 2 { "a" } else { "b" };
            let out = dir.path().join("shards");
            datagen::pairs::generator::write_shard(&out, &format!("{shard}{seed}"), &records, digest).unwrap();
        }
        dir
    })
    .path()
}

fn config(batch_size: usize, rank: usize, world_size: usize) -> DataConfig {
    DataConfig {
        frames: 5,
        height: 24,
        width: 40,
        batch_size,
        seed: 9,
        rank,
        world_size,
        prefetch_batches: 2,
        multiview_share: None,
    }
}

fn dirs() -> Vec<PathBuf> {
    vec![shards().join("shards")]
}

#[test]
fn batches_have_the_training_shape_and_consistent_values() {
    let mut loader = ShardLoader::open(&dirs(), config(2, 0, 1), DataPosition::default()).unwrap();
    assert_eq!(loader.batches_per_epoch(), 3, "6 clips in batches of 2");
    let batch = loader.next_batch().unwrap();
    assert_eq!(batch.target.size(), vec![2, 3, 5, 24, 40]);
    assert_eq!(batch.condition.size(), vec![2, 3, 5, 24, 40]);
    assert_eq!(batch.mask.size(), vec![2, 1, 5, 24, 40]);
    assert_eq!(batch.target.kind(), Kind::Float);
    let (lo, hi) = (batch.target.min().double_value(&[]), batch.target.max().double_value(&[]));
    assert!((-1.0..=1.0).contains(&lo) && (-1.0..=1.0).contains(&hi) && hi > lo);
    // Without depth noise the conditioning is the target where co-visible and black elsewhere.
    let expected = &batch.target * &batch.mask + (batch.mask.ones_like() - &batch.mask) * -1.0;
    let err = (&batch.condition - expected).abs().max().double_value(&[]);
    assert!(err < 1e-6, "{err}");
    let kept = batch.mask.mean(Kind::Float).double_value(&[]);
    assert!(kept > 0.2 && kept < 1.0, "co-visible fraction {kept}");
    assert!(batch.provenance.iter().all(|p| p.starts_with("synth/seq")), "{:?}", batch.provenance);
}

fn provenance(loader: &mut ShardLoader, batches: usize) -> Vec<Vec<String>> {
    (0..batches).map(|_| loader.next_batch().unwrap().provenance).collect()
}

#[test]
fn order_is_deterministic_and_resume_is_exact() {
    let mut a = ShardLoader::open(&dirs(), config(1, 0, 1), DataPosition::default()).unwrap();
    let mut b = ShardLoader::open(&dirs(), config(1, 0, 1), DataPosition::default()).unwrap();
    let first = provenance(&mut a, 9);
    assert_eq!(first, provenance(&mut b, 9), "same seed, same batches");
    // One epoch visits every clip once, the next one in another order.
    let epoch0: BTreeSet<String> = first[..6].iter().map(|p| p[0].split('#').next().unwrap().to_string()).collect();
    assert_eq!(epoch0.len(), 6);
    // Resume from the position after 4 batches: the same batches and tensors follow.
    let mut reference = ShardLoader::open(&dirs(), config(1, 0, 1), DataPosition::default()).unwrap();
    let mut position = DataPosition::default();
    let mut expected = Vec::new();
    for i in 0..8 {
        let batch = reference.next_batch().unwrap();
        if i == 3 {
            position = reference.position();
        }
        if i >= 4 {
            expected.push(batch);
        }
    }
    assert_eq!(position, DataPosition { epoch: 0, batch: 4 });
    let mut resumed = ShardLoader::open(&dirs(), config(1, 0, 1), position).unwrap();
    for want in expected {
        let got = resumed.next_batch().unwrap();
        assert_eq!(got.provenance, want.provenance);
        assert_eq!(got.position, want.position);
        assert!(got.target.equal(&want.target) && got.condition.equal(&want.condition) && got.mask.equal(&want.mask));
    }
    let mut other_seed =
        ShardLoader::open(&dirs(), DataConfig { seed: 10, ..config(1, 0, 1) }, DataPosition::default()).unwrap();
    assert_ne!(provenance(&mut other_seed, 6), first[..6].to_vec());
}

#[test]
fn ranks_split_each_epoch_disjointly_and_completely() {
    let clips = |loader: &mut ShardLoader| -> BTreeSet<String> {
        provenance(loader, 3).into_iter().flatten().map(|p| p.split('#').next().unwrap().to_string()).collect()
    };
    let mut rank0 = ShardLoader::open(&dirs(), config(1, 0, 2), DataPosition::default()).unwrap();
    let mut rank1 = ShardLoader::open(&dirs(), config(1, 1, 2), DataPosition::default()).unwrap();
    assert_eq!(rank0.batches_per_epoch(), 3);
    let (a, b) = (clips(&mut rank0), clips(&mut rank1));
    assert!(a.is_disjoint(&b), "{a:?} {b:?}");
    assert_eq!(a.union(&b).count(), 6);
}

#[test]
fn bad_shard_folders_are_named_errors() {
    let empty = tempfile::tempdir().unwrap();
    let err = ShardLoader::open(&[empty.path().to_path_buf()], config(1, 0, 1), DataPosition::default())
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("no *.parquet shards") && err.contains(&empty.path().display().to_string()), "{err}");
    let err = ShardLoader::open(&dirs(), config(7, 0, 1), DataPosition::default()).err().unwrap().to_string();
    assert!(err.contains("batch_size") && err.contains("6 clips"), "{err}");
    // A Parquet file of another schema, finished with a stats marker.
    let foreign = empty.path().join("other.parquet");
    std::fs::write(&foreign, b"PAR1 not really").unwrap();
    std::fs::write(schemas::stats_path(&foreign), b"{}").unwrap();
    let err = ShardLoader::open(&[empty.path().to_path_buf()], config(1, 0, 1), DataPosition::default())
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("other.parquet"), "{err}");
}

/// The shards of [`shards`] plus one of a synthetic 3-camera scene (generated once): its 3
/// cameras' monocular clips and the 6 camera pairs' multi-view clips, 5 frames each.
fn mixed_shards() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("mixed");
        for entry in std::fs::read_dir(shards().join("shards")).unwrap() {
            let path = entry.unwrap().path();
            std::fs::copy(&path, out_path(&out, &path)).unwrap();
        }
        let scene = datagen::synth::SynthConfig { width: 48, height: 32, frames: 5, ..Default::default() };
        let rig = datagen::synth::CameraRig { cameras: 3, spacing_deg: 8.0 };
        let folder = datagen::synth::write_multiview(&scene, &rig, &dir.path().join("rig"), |_| {}).unwrap();
        let mut pairs = datagen::pairs::generator::PairsConfig::default();
        pairs.clip.length = 5;
        datagen::pairs::scene::write_scene_pairs(&folder, &out, "synth", &pairs, 1, 4, &mut |_| {}).unwrap();
        dir
    })
    .path()
}

fn out_path(out: &Path, path: &Path) -> PathBuf {
    std::fs::create_dir_all(out).unwrap();
    out.join(path.file_name().unwrap())
}

fn mixed(batch_size: usize, rank: usize, world_size: usize, share: f64) -> DataConfig {
    DataConfig { multiview_share: Some(share), ..config(batch_size, rank, world_size) }
}

#[test]
fn a_multiview_share_is_kept_per_batch_and_ranks_1_and_2_see_one_sequence() {
    let dirs = vec![mixed_shards().join("mixed")];
    // 6 + 3 monocular clips, 6 multi-view ones. A global batch of 4 at 0.3 holds 1.2 multi-view
    // slots on average: the running total rounds to 1, 2, 4, 5, 6, ..., so batches hold 1, 1, 2,
    // 1, 1; monocular slots then run out first: 3 batches take 8 of the 9.
    let mut one = ShardLoader::open(&dirs, mixed(4, 0, 1, 0.3), DataPosition::default()).unwrap();
    assert_eq!(one.batches_per_epoch(), 3);
    let global = provenance(&mut one, 6);
    let is_multiview = |p: &String| p.contains("/from-");
    let counts: Vec<usize> = global.iter().map(|b| b.iter().filter(|p| is_multiview(p)).count()).collect();
    assert_eq!(counts, [1, 1, 2, 1, 1, 2]);
    let clip = |p: &String| p.split('#').next().unwrap().to_string();
    let (multiview, monocular): (Vec<&String>, Vec<&String>) =
        global[..3].iter().flatten().partition(|p| is_multiview(p));
    assert_eq!(multiview.iter().map(|p| clip(p)).collect::<BTreeSet<_>>().len(), 4, "no clip twice in an epoch");
    assert_eq!(monocular.iter().map(|p| clip(p)).collect::<BTreeSet<_>>().len(), 8, "no clip twice in an epoch");

    // Two ranks with half the batch each: rank r takes global slots r, r + 2, ... of the same draw.
    let mut rank0 = ShardLoader::open(&dirs, mixed(2, 0, 2, 0.3), DataPosition::default()).unwrap();
    let mut rank1 = ShardLoader::open(&dirs, mixed(2, 1, 2, 0.3), DataPosition::default()).unwrap();
    assert_eq!(rank0.batches_per_epoch(), 3);
    let (a, b) = (provenance(&mut rank0, 6), provenance(&mut rank1, 6));
    for (i, batch) in global.iter().enumerate() {
        let interleaved = vec![a[i][0].clone(), b[i][0].clone(), a[i][1].clone(), b[i][1].clone()];
        assert_eq!(&interleaved, batch, "batch {i}");
    }

    // A multi-view sample's conditioning is the stored render, not the target × mask.
    let mut all_multiview = ShardLoader::open(&dirs, mixed(2, 0, 1, 1.0), DataPosition::default()).unwrap();
    assert_eq!(all_multiview.batches_per_epoch(), 3);
    let batch = all_multiview.next_batch().unwrap();
    assert!(batch.provenance.iter().all(is_multiview), "{:?}", batch.provenance);
    let masked_target = &batch.target * &batch.mask + (batch.mask.ones_like() - &batch.mask) * -1.0;
    let differs = (&batch.condition - masked_target).abs().max().double_value(&[]);
    assert!(differs > 0.01, "another camera's render differs from the target somewhere: {differs}");
    let outside = ((&batch.condition + 1.0) * (batch.mask.ones_like() - &batch.mask)).abs().max().double_value(&[]);
    assert!(outside < 1e-6, "black outside the mask: {outside}");

    // Unset, every clip in one order, as before the mix existed.
    let unmixed = ShardLoader::open(&dirs, config(3, 0, 1), DataPosition::default()).unwrap();
    assert_eq!(unmixed.batches_per_epoch(), 5, "15 clips in batches of 3");
}

#[test]
fn a_multiview_share_without_multiview_pairs_is_an_error_naming_the_key() {
    let err = ShardLoader::open(
        &dirs(),
        DataConfig { multiview_share: Some(0.25), ..config(1, 0, 1) },
        DataPosition::default(),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(err.contains("data.multiview_share") && err.contains("multi-view"), "{err}");
    // The range is checked too; 0 is a share like any other (monocular pairs only).
    let err = ShardLoader::open(
        &dirs(),
        DataConfig { multiview_share: Some(1.5), ..config(1, 0, 1) },
        DataPosition::default(),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(err.contains("data.multiview_share") && err.contains("[0, 1]"), "{err}");
    let mut monocular = ShardLoader::open(
        &[mixed_shards().join("mixed")],
        DataConfig { multiview_share: Some(0.0), ..config(3, 0, 1) },
        DataPosition::default(),
    )
    .unwrap();
    assert_eq!(monocular.batches_per_epoch(), 3, "9 monocular clips in batches of 3");
    let batch = monocular.next_batch().unwrap();
    assert!(batch.provenance.iter().all(|p| !p.contains("/from-")), "{:?}", batch.provenance);
}
