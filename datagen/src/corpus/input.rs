//! Turning a crawled video into training pairs: its frames (video or image folder), its
//! reconstruction and its dynamic-object masks become a [`Sequence`], which the pair generator
//! cuts into clips.
//!
//! Frame rates: frames are used as stored. SA-V videos keep their 24 fps (stored with the
//! clips); image datasets (TAO, YouTube-VOS, DAVIS) have no rate in their files, so clips record
//! 0 (unknown) and a clip is a window of consecutive stored frames.

use std::sync::Mutex;
use std::time::Instant;

use image::GrayImage;
use rayon::prelude::*;

use super::build::{BuildConfig, InputProcessor, Outcome};
use super::crawl::{FrameSource, MaskSource, VideoEntry};
use crate::error::{Error, Result};
use crate::io::annotations::{
    box_frame_masks, fill_between_annotations, load_sav_annotation, read_id_png, sav_frame_masks,
};
use crate::io::layout::LayoutName;
use crate::io::sequence::{Sequence, read_sequence_as, read_with_frames_as};
use crate::pairs::generator::{PhaseTimes, TrajectoryRequest, generate_clips_timed};
use foundation::frames::read_frames;

/// Loads everything the pair generator needs for one crawled video.
pub fn load_entry(entry: &VideoEntry) -> Result<Sequence> {
    load_entry_as(entry, None)
}

/// [`load_entry`] with its folder or reconstruction read in `layout` where that is a
/// single-camera layout (detected otherwise: [`BuildConfig::layout`]).
pub fn load_entry_as(entry: &VideoEntry, layout: Option<LayoutName>) -> Result<Sequence> {
    let layout = layout.and_then(LayoutName::sequence);
    let key = entry.key();
    let reconstruction = entry
        .reconstruction
        .as_ref()
        .ok_or_else(|| Error::invalid(&key, "reconstruction", "no reconstruction found for this video"))?;
    let mut sequence = match &entry.frames {
        FrameSource::Sequence(dir) => {
            // The folder's own name is not unique in a nested tree (`a/seq`, `b/seq`); the
            // video id is (keys are checked unique per build), and clip ids and seeds derive from it.
            let mut sequence = read_sequence_as(dir, layout)?;
            sequence.source_id = entry.video_id.clone();
            return Ok(sequence);
        }
        FrameSource::MultiView(dir) => {
            return Err(Error::invalid(
                dir,
                "cameras",
                "a multi-camera scene is not one sequence (read it as a scene)",
            ));
        }
        FrameSource::Video(path) => {
            let video = foundation::video::decode_video(path)?;
            read_with_frames_as(&entry.video_id, reconstruction, layout, video.fps, video.frames, path)?
        }
        FrameSource::Images(paths) => {
            let frames = read_frames(paths)?;
            let folder = paths.first().and_then(|p| p.parent()).unwrap_or(reconstruction);
            read_with_frames_as(&entry.video_id, reconstruction, layout, 0.0, frames, folder)?
        }
    };
    let (width, height) = sequence.size();
    let frame_count = sequence.len();
    let fit = |mask: GrayImage| {
        if mask.dimensions() == (width, height) {
            mask
        } else {
            image::imageops::resize(&mask, width, height, image::imageops::FilterType::Nearest)
        }
    };
    let masks = match &entry.masks {
        MaskSource::None => None,
        MaskSource::Sav(json) => Some(sav_frame_masks(&load_sav_annotation(json)?, frame_count, json)?),
        MaskSource::IdPngs(dir) => {
            // Matched to frames by file stem (YouTube-VOS annotates a subset of frames).
            let stems: Vec<String> = match &entry.frames {
                FrameSource::Images(paths) => {
                    paths.iter().map(|p| p.file_stem().unwrap_or_default().to_string_lossy().into_owned()).collect()
                }
                _ => (0..frame_count).map(|i| format!("{i:05}")).collect(),
            };
            let annotated = stems
                .par_iter()
                .map(|stem| {
                    let path = dir.join(format!("{stem}.png"));
                    if path.is_file() { read_id_png(&path).map(Some) } else { Ok(None) }
                })
                .collect::<Result<Vec<_>>>()?;
            fill_between_annotations(annotated)
        }
        MaskSource::Boxes { boxes, width: box_width, height: box_height } => {
            Some(box_frame_masks(boxes, frame_count, *box_width, *box_height))
        }
    };
    sequence.dynamic_masks = masks.map(|m| m.into_iter().map(fit).collect());
    Ok(sequence)
}

/// Where a build's processing time went, summed over inputs.
#[derive(Debug, Clone, Copy, Default)]
pub struct ProcessTimings {
    /// Wall seconds decoding frames and reading reconstructions and annotations.
    pub load_seconds: f64,
    /// The pair generator's phases (mesh builds, rays, encoding).
    pub pairs: PhaseTimes,
}

/// The build's processor: load the video, generate its clips with the configured trajectories.
pub struct SequenceProcessor<'a> {
    config: &'a BuildConfig,
    timings: Mutex<ProcessTimings>,
}

impl<'a> SequenceProcessor<'a> {
    /// A processor for `config`.
    pub fn new(config: &'a BuildConfig) -> Self {
        Self { config, timings: Mutex::default() }
    }

    /// Where the processing time went so far.
    pub fn timings(&self) -> ProcessTimings {
        *self.timings.lock().expect("timings lock")
    }
}

impl SequenceProcessor<'_> {
    /// A multi-camera scene: its monocular and multi-view pairs ([`crate::pairs::multiview`]).
    /// A scene the reader refuses is an error, so the build records it as failed and writes
    /// nothing for it. The reconstruction filter (`[check]`) judges single sequences and is not
    /// applied to scenes.
    fn process_scene(&self, entry: &VideoEntry, dir: &std::path::Path) -> Result<Outcome> {
        let started = Instant::now();
        let layout = self.config.layout.and_then(LayoutName::multiview);
        let mut scene = crate::io::layout::read_multiview_as(dir, layout)?;
        // Keys, clip ids and seeds derive from the video id, unique in the build.
        scene.scene_id = entry.video_id.clone();
        let load_seconds = started.elapsed().as_secs_f64();
        let clock = Instant::now();
        let pairs = crate::pairs::scene::generate_scene_clips(
            &scene,
            entry.dataset.name(),
            &self.config.pairs,
            self.config.trajectories,
            self.config.seed,
            &mut |_| {},
        )?;
        let mut timings = self.timings.lock().expect("timings lock");
        timings.load_seconds += load_seconds;
        timings.pairs.masks_and_encode += clock.elapsed().as_secs_f64();
        Ok(Outcome::Clips(pairs.records))
    }
}

impl InputProcessor for SequenceProcessor<'_> {
    fn process(&self, entry: &VideoEntry) -> Result<Outcome> {
        if let FrameSource::MultiView(dir) = &entry.frames {
            return self.process_scene(entry, dir);
        }
        let started = Instant::now();
        let mut sequence = load_entry_as(entry, self.config.layout)?;
        let noise = &self.config.pairs.depth_noise;
        noise.load_second_depth(&mut sequence, None, entry.dataset.name(), &entry.dataset_id)?;
        let load_seconds = started.elapsed().as_secs_f64();
        if let Some(reason) =
            super::quality::filter(&self.config.check, &self.config.output.dir, &entry.key(), &sequence)?
        {
            return Ok(Outcome::Skipped(reason));
        }
        let request = TrajectoryRequest { sampled: self.config.trajectories, explicit: Vec::new() };
        let (clips, phases) =
            generate_clips_timed(&sequence, entry.dataset.name(), &self.config.pairs, &request, self.config.seed)?;
        let mut timings = self.timings.lock().expect("timings lock");
        timings.load_seconds += load_seconds;
        timings.pairs.add(&phases);
        Ok(Outcome::Clips(clips))
    }
}
