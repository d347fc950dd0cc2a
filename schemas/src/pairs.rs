//! The training-pair shard schema: one Parquet row per source clip, holding the clip's
//! frames, depth and cameras once, and a list of trajectories, each with its novel cameras,
//! sampling parameters and lossless co-visibility masks.
//!
//! Every field carries its documentation in the Arrow field metadata (key [`DOC_KEY`]), so the
//! reference in `schemas/SCHEMA.md` is generated from this file and readers in Python see the same
//! text in `pyarrow` (`schema.field(name).metadata`).

use std::collections::HashMap;
use std::sync::Arc;

use arrow_schema::{DataType, Field, Fields, Schema};

/// Parquet key-value metadata key naming which schema a file follows.
pub const SCHEMA_NAME_KEY: &str = "cognvs.schema";
/// Value of [`SCHEMA_NAME_KEY`] for training-pair shards.
pub const SCHEMA_NAME: &str = "cognvs.pairs";
/// Parquet key-value metadata key holding the schema version (a decimal integer).
pub const SCHEMA_VERSION_KEY: &str = "cognvs.schema_version";
/// The version this code writes. Bump on any change a reader could notice. Version 2 added
/// `trajectories[].bank_entry` and the trajectory kind `bank`; version 3 the pair kind
/// (`pair_kind`, `source_camera`, `target_camera`) and the trajectory kind `camera`; version 4
/// `trajectories[].mask_rule`.
pub const SCHEMA_VERSION: u32 = 4;
/// The oldest version this code still reads (older shards lack the columns added since, which
/// read as null).
pub const OLDEST_READABLE_SCHEMA_VERSION: u32 = 1;
/// The first version with `trajectories[].bank_entry`.
const BANK_ENTRY_SINCE: u32 = 2;
/// The first version with `pair_kind`, `source_camera` and `target_camera`.
pub const PAIR_KIND_SINCE: u32 = 3;
/// The first version with `trajectories[].mask_rule`.
pub const MASK_RULE_SINCE: u32 = 4;
/// Arrow field metadata key holding a field's documentation.
pub const DOC_KEY: &str = "doc";

/// Where a trajectory came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrajectoryKind {
    /// Sampled by the generator from spherical offsets about the pivot (the paper's sampler).
    Sampled,
    /// Given by the user as per-frame cameras or a `trajs/*.txt` file.
    Explicit,
    /// The source path composed with a trajectory bank entry's real camera motion (schema v2+).
    Bank,
    /// Another real camera of a synchronised multi-camera scene (multi-view pairs, schema v3+).
    Camera,
}

impl TrajectoryKind {
    /// The string stored in the `kind` column.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Sampled => "sampled",
            Self::Explicit => "explicit",
            Self::Bank => "bank",
            Self::Camera => "camera",
        }
    }

    /// Parses the `kind` column's value.
    pub fn parse(value: &str) -> Option<Self> {
        match value {
            "sampled" => Some(Self::Sampled),
            "explicit" => Some(Self::Explicit),
            "bank" => Some(Self::Bank),
            "camera" => Some(Self::Camera),
            _ => None,
        }
    }
}

/// What a clip's pairs are made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PairKind {
    /// Self-supervised from one camera: the target is the source video, the conditioning that video
    /// masked to what a novel camera sees (every shard before v3).
    #[default]
    Monocular,
    /// From a synchronised multi-camera scene: the target is camera `target_camera`'s real frames,
    /// the conditioning camera `source_camera`'s frames rendered into it (schema v3+).
    Multiview,
}

impl PairKind {
    /// The string stored in the `pair_kind` column.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Monocular => "monocular",
            Self::Multiview => "multiview",
        }
    }

    /// Parses the `pair_kind` column's value.
    pub fn parse(value: &str) -> Option<Self> {
        match value {
            "monocular" => Some(Self::Monocular),
            "multiview" => Some(Self::Multiview),
            _ => None,
        }
    }
}

/// Which rule made a trajectory's masks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MaskRule {
    /// Exact visibility against the source's depth mesh: for monocular pairs, the source pixels
    /// whose surface point the novel camera sees; for multi-view pairs, the target pixels whose
    /// surface point (from the target's depth) is the first surface the source camera sees.
    Exact,
    /// The target pixels that the source's render covers (multi-view pairs whose target has no
    /// depth; every multi-view pair before v4).
    Coverage,
    /// The dataset's own co-visibility masks of the target (DyCheck's `covisible/`, for its
    /// held-out cameras seen from its input camera).
    Dataset,
}

impl MaskRule {
    /// The string stored in the `mask_rule` column.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Exact => "exact",
            Self::Coverage => "coverage",
            Self::Dataset => "dataset",
        }
    }

    /// Parses the `mask_rule` column's value.
    pub fn parse(value: &str) -> Option<Self> {
        match value {
            "exact" => Some(Self::Exact),
            "coverage" => Some(Self::Coverage),
            "dataset" => Some(Self::Dataset),
            _ => None,
        }
    }

    /// The rule that made the masks of shards older than v4, which do not record it: the exact
    /// kernel for monocular pairs, the render's coverage for multi-view pairs.
    pub fn before_v4(pair_kind: PairKind) -> Self {
        match pair_kind {
            PairKind::Monocular => Self::Exact,
            PairKind::Multiview => Self::Coverage,
        }
    }
}

/// Which trajectory bank entry a `bank` trajectory was drawn from, and how it was varied.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BankProvenance {
    /// The entry's `entry_id` in the bank (`{dataset}/{video_id}/{window_start}`).
    pub entry_id: String,
    /// The entry's row in the bank file (0-based).
    pub entry_row: u32,
    /// BLAKE3 hex digest of the bank file.
    pub bank_digest: String,
    /// Whether the motion was mirrored left/right.
    pub mirrored: bool,
    /// Rotation of the motion about the viewing axis, in degrees.
    pub roll_deg: f64,
}

/// One novel camera path for a clip, with its co-visibility masks.
#[derive(Debug, Clone, PartialEq)]
pub struct TrajectoryRecord {
    /// Position of this trajectory within the clip (0-based, stable: it seeds the sampling).
    pub index: u32,
    /// Sampled or user-given.
    pub kind: TrajectoryKind,
    /// Orbit pivot distance R along each source camera's optical axis, in depth units.
    pub pivot_distance: f64,
    /// Azimuth control values in degrees (4 for sampled trajectories; per-frame values for a
    /// `trajs/*.txt` input; empty for explicit camera lists).
    pub azimuth_deg: Vec<f64>,
    /// Elevation control values in degrees, like `azimuth_deg`.
    pub elevation_deg: Vec<f64>,
    /// Radial offset control values as fractions of R, like `azimuth_deg`.
    pub radius_frac: Vec<f64>,
    /// How many sampled candidates were rejected (camera path crossing the surface) before this one.
    pub rejected_samples: u32,
    /// Per-frame novel camera pose, `world_from_camera`, row-major 4×4.
    pub world_from_camera: Vec<[f64; 16]>,
    /// Per-frame co-visibility mask as 8-bit greyscale PNG: 255 co-visible, 0 hidden.
    pub covisible_mask: Vec<Vec<u8>>,
    /// Per-frame conditioning frames as RGB PNG when they differ from `frames × mask` (depth
    /// noise); `None` means the conditioning is exactly the clip's frames with hidden pixels black.
    pub condition: Option<Vec<Vec<u8>>>,
    /// Fraction of the clip's valid pixels that are co-visible, over all frames.
    pub covisible_fraction: f64,
    /// For `bank` trajectories, the bank entry they came from; `None` otherwise (and in v1 shards).
    pub bank_entry: Option<BankProvenance>,
    /// Which rule made `covisible_mask` (in shards before v4, [`MaskRule::before_v4`]).
    pub mask_rule: MaskRule,
}

/// One clip of a source video with everything needed to train on it.
#[derive(Debug, Clone, PartialEq)]
pub struct ClipRecord {
    /// Unique id of the clip within a corpus: `{dataset}/{source_id}/{clip_start}`.
    pub clip_id: String,
    /// Id of the source video within its dataset.
    pub source_id: String,
    /// Dataset name (`sav`, `tao`, `ytvos`, `davis`, `synth`, `sequence`, ...).
    pub dataset: String,
    /// Path of the input sequence as the generator saw it.
    pub source_path: String,
    /// Index of the clip's first frame in the source video.
    pub clip_start: u32,
    /// Frame rate of the source video (frames per second; 0 if unknown).
    pub fps: f64,
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// The generator's seed (combined with ids to derive every random choice).
    pub seed: u64,
    /// Name and version of the tool that wrote the record, e.g. `datagen 0.1.0`.
    pub tool_version: String,
    /// Per-frame RGB frames as PNG: the training target.
    pub frames: Vec<Vec<u8>>,
    /// Per-frame z-depth as single-channel (`Z`) f32 OpenEXR, at frame resolution.
    pub depth: Vec<Vec<u8>>,
    /// Per-frame intrinsics K in pixels, row-major 3×3, pixel centres at integer coordinates.
    pub intrinsics: Vec<[f64; 9]>,
    /// Per-frame source camera pose, `world_from_camera`, row-major 4×4, OpenCV axes.
    pub world_from_camera: Vec<[f64; 16]>,
    /// Per-frame dynamic-object masks as 8-bit greyscale PNG (0 static, >0 object id, 255 void).
    pub dynamic_mask: Option<Vec<Vec<u8>>>,
    /// The clip's trajectories.
    pub trajectories: Vec<TrajectoryRecord>,
    /// Monocular (self-supervised) or multi-view pairs (`monocular` in shards before v3).
    pub pair_kind: PairKind,
    /// The camera whose frames are rendered into the conditioning: for multi-view pairs the
    /// source camera's id, for monocular pairs of a multi-camera scene the filming camera's id;
    /// `None` for single-camera inputs (and in shards before v3).
    pub source_camera: Option<String>,
    /// The camera whose frames are the target (`frames`): its id in a multi-camera scene; `None`
    /// for single-camera inputs (and in shards before v3).
    pub target_camera: Option<String>,
}

impl ClipRecord {
    /// Number of frames of the clip.
    pub fn num_frames(&self) -> usize {
        self.frames.len()
    }
}

fn doc(field: Field, text: &str) -> Field {
    field.with_metadata(HashMap::from([(DOC_KEY.to_owned(), text.to_owned())]))
}

/// `list<item>` with a non-null item of the given type.
fn list_of(item: DataType) -> DataType {
    DataType::List(Arc::new(Field::new("item", item, false)))
}

/// `list<fixed_size_list<float64, n>>`: one small matrix per frame.
pub(crate) fn per_frame_matrix(n: i32) -> DataType {
    list_of(DataType::FixedSizeList(Arc::new(Field::new("item", DataType::Float64, false)), n))
}

/// `list<large_binary>`: one encoded image per frame.
pub(crate) fn per_frame_bytes() -> DataType {
    list_of(DataType::LargeBinary)
}

/// The fields of one element of the `trajectories` column's `bank_entry` struct.
pub fn bank_provenance_fields() -> Fields {
    Fields::from(vec![
        doc(
            Field::new("entry_id", DataType::Utf8, false),
            "The bank entry's `entry_id` (`{dataset}/{video_id}/{window_start}`).",
        ),
        doc(Field::new("entry_row", DataType::UInt32, false), "The entry's row in the bank file (0-based)."),
        doc(Field::new("bank_digest", DataType::Utf8, false), "BLAKE3 hex digest of the bank file."),
        doc(Field::new("mirrored", DataType::Boolean, false), "Whether the motion was mirrored left/right."),
        doc(
            Field::new("roll_deg", DataType::Float64, false),
            "Rotation of the motion about the viewing axis, in degrees.",
        ),
    ])
}

/// The fields of one element of the `trajectories` column (this code's version).
pub fn trajectory_fields() -> Fields {
    trajectory_fields_of_version(SCHEMA_VERSION)
}

/// The fields of one element of the `trajectories` column as schema `version` has them.
pub fn trajectory_fields_of_version(version: u32) -> Fields {
    let mut fields = vec![
        doc(
            Field::new("index", DataType::UInt32, false),
            "Position of the trajectory within the clip (0-based); part of its seed.",
        ),
        doc(
            Field::new("kind", DataType::Utf8, false),
            "`sampled` (spherical offsets drawn by the generator), `explicit` (given by the user), `bank` (the source path composed with a trajectory bank entry's motion; v2+) or `camera` (another real camera of a multi-camera scene: multi-view pairs; v3+).",
        ),
        doc(
            Field::new("pivot_distance", DataType::Float64, false),
            "Orbit pivot distance R along each source camera's optical axis, in the reconstruction's depth units.",
        ),
        doc(
            Field::new("azimuth_deg", list_of(DataType::Float64), false),
            "Azimuth control values in degrees: 4 for sampled trajectories, per-frame for `trajs/*.txt` input, empty for explicit camera lists.",
        ),
        doc(
            Field::new("elevation_deg", list_of(DataType::Float64), false),
            "Elevation control values in degrees, laid out like `azimuth_deg`.",
        ),
        doc(
            Field::new("radius_frac", list_of(DataType::Float64), false),
            "Radial offset control values as fractions of R, laid out like `azimuth_deg`.",
        ),
        doc(
            Field::new("rejected_samples", DataType::UInt32, false),
            "Sampled candidates rejected (camera path crossing the reconstructed surface) before this one.",
        ),
        doc(
            Field::new("world_from_camera", per_frame_matrix(16), false),
            "Per-frame novel camera pose `world_from_camera`, row-major 4×4, OpenCV axes (x right, y down, z forward).",
        ),
        doc(
            Field::new("covisible_mask", per_frame_bytes(), false),
            "Per-frame co-visibility mask, 8-bit greyscale PNG: 255 where the source pixel's surface point is visible from the novel camera, 0 elsewhere.",
        ),
        doc(
            Field::new("condition", per_frame_bytes(), true),
            "Per-frame conditioning frames (RGB PNG) when they differ from `frames` × mask (depth noise); null means exactly `frames` with hidden pixels black.",
        ),
        doc(
            Field::new("covisible_fraction", DataType::Float64, false),
            "Fraction of the clip's pixels that are co-visible, over all frames.",
        ),
    ];
    if version >= BANK_ENTRY_SINCE {
        fields.push(doc(
            Field::new("bank_entry", DataType::Struct(bank_provenance_fields()), true),
            "For `bank` trajectories: the trajectory bank entry drawn and how it was varied; null otherwise (added in v2).",
        ));
    }
    if version >= MASK_RULE_SINCE {
        fields.push(doc(
            Field::new("mask_rule", DataType::Utf8, false),
            "Which rule made `covisible_mask`: `exact` (exact visibility against the source's depth mesh: monocular pairs keep the source pixels whose surface point the novel camera sees, multi-view pairs the target pixels whose surface point, from the target's depth, is the first surface the source camera sees), `coverage` (multi-view pairs whose target has no depth: the target pixels the source's render covers) or `dataset` (the dataset's own co-visibility masks, DyCheck's `covisible/`). Added in v4; older shards read as `exact` for monocular and `coverage` for multi-view pairs.",
        ));
    }
    Fields::from(fields)
}

/// The Arrow schema of a training-pair shard, with the schema name and version in its metadata.
pub fn pair_schema() -> Schema {
    pair_schema_of_version(SCHEMA_VERSION)
}

/// The Arrow schema of a training-pair shard of schema `version` (for reading older shards).
pub fn pair_schema_of_version(version: u32) -> Schema {
    let mut fields = vec![
        doc(
            Field::new("clip_id", DataType::Utf8, false),
            "Unique id of the clip within a corpus: `{dataset}/{source_id}/{clip_start}`.",
        ),
        doc(Field::new("source_id", DataType::Utf8, false), "Id of the source video within its dataset."),
        doc(
            Field::new("dataset", DataType::Utf8, false),
            "Dataset name: `sav`, `tao`, `ytvos`, `davis`, `synth`, `sequence`, ...",
        ),
        doc(Field::new("source_path", DataType::Utf8, false), "Path of the input sequence as the generator saw it."),
        doc(
            Field::new("clip_start", DataType::UInt32, false),
            "Index of the clip's first frame in the source video (frames numbered from 0).",
        ),
        doc(
            Field::new("num_frames", DataType::UInt32, false),
            "Number of frames of the clip; every per-frame list has this length.",
        ),
        doc(
            Field::new("fps", DataType::Float64, false),
            "Frame rate of the source video in frames per second (0 if unknown).",
        ),
        doc(Field::new("width", DataType::UInt32, false), "Frame width in pixels."),
        doc(Field::new("height", DataType::UInt32, false), "Frame height in pixels."),
        doc(
            Field::new("seed", DataType::UInt64, false),
            "Generator seed; every random choice derives from it plus stable ids (source id, clip start, trajectory index).",
        ),
        doc(
            Field::new("tool_version", DataType::Utf8, false),
            "Name and version of the tool that wrote the row, e.g. `datagen 0.1.0`.",
        ),
        doc(
            Field::new("frames", per_frame_bytes(), false),
            "Per-frame RGB frames as PNG (8 bits per channel): the training target, stored once per clip.",
        ),
        doc(
            Field::new("depth", per_frame_bytes(), false),
            "Per-frame z-depth along the optical axis as single-channel (`Z`) 32-bit float OpenEXR at frame resolution; invalid depth is ≤ 0, NaN or inf.",
        ),
        doc(
            Field::new("intrinsics", per_frame_matrix(9), false),
            "Per-frame intrinsics K in pixels, row-major 3×3; pixel centres at integer coordinates (centred principal point: cx = W/2 − 0.5).",
        ),
        doc(
            Field::new("world_from_camera", per_frame_matrix(16), false),
            "Per-frame source camera pose `world_from_camera`, row-major 4×4, OpenCV axes (x right, y down, z forward).",
        ),
        doc(
            Field::new("dynamic_mask", per_frame_bytes(), true),
            "Per-frame dynamic-object masks, 8-bit greyscale PNG: 0 static, >0 object id, 255 void; null when the input has none.",
        ),
        doc(
            Field::new("trajectories", list_of(DataType::Struct(trajectory_fields_of_version(version))), false),
            "The clip's novel camera paths; each element is one training pair (conditioning → `frames`).",
        ),
    ];
    if version >= PAIR_KIND_SINCE {
        fields.extend([
            doc(
                Field::new("pair_kind", DataType::Utf8, false),
                "`monocular` (self-supervised: the target is the source video, the conditioning it masked to a novel camera's view) or `multiview` (the target is camera `target_camera`'s real frames, the conditioning camera `source_camera`'s frames rendered into it; the trajectory, of kind `camera`, is the source camera's path and its `condition` is always stored). Added in v3; older shards read as `monocular`.",
            ),
            doc(
                Field::new("source_camera", DataType::Utf8, true),
                "Multi-view pairs: the source camera's id; monocular pairs of a multi-camera scene: the filming camera's id; null for single-camera inputs (added in v3).",
            ),
            doc(
                Field::new("target_camera", DataType::Utf8, true),
                "The id of the camera whose frames are `frames`, in a multi-camera scene; null for single-camera inputs (added in v3).",
            ),
        ]);
    }
    Schema::new(fields).with_metadata(HashMap::from([
        (SCHEMA_NAME_KEY.to_owned(), SCHEMA_NAME.to_owned()),
        (SCHEMA_VERSION_KEY.to_owned(), version.to_string()),
    ]))
}
