//! Blocks cut into sub-blocks short enough that the camera barely moves inside one, and long
//! enough to collect photons (this project's stage; the paper keeps whole blocks, §4.1).
#![forbid(unsafe_code)]

use super::config::RefineConfig;
use super::frame_motion::FrameMotion;

/// The shortest sub-block [`plan_sub_blocks`] cuts (frames): `max(min_sub_block_frames,
/// min_sub_block_counts / detections_per_frame)`, at least 1.
pub fn shortest_sub_block(detections_per_frame: f64, config: &RefineConfig) -> usize {
    let by_light = if detections_per_frame > 0.0 {
        (config.min_sub_block_counts / detections_per_frame).ceil() as usize
    } else {
        usize::MAX
    };
    by_light.max(config.min_sub_block_frames).max(1)
}

/// Cuts every block of `motion` (one sub-block per block, as from
/// [`FrameMotion::from_alignment`]) into equal sub-blocks so that the camera moves at most
/// `config.max_sub_block_motion_px` inside each, never shorter than
/// `max(min_sub_block_frames, min_sub_block_counts / detections_per_frame)` frames; each
/// sub-block starts at the block motion interpolated to its centre.
pub fn plan_sub_blocks(motion: &mut FrameMotion, detections_per_frame: f64, config: &RefineConfig) {
    let shortest = shortest_sub_block(detections_per_frame, config);
    let half = motion.half_size();
    let pieces: Vec<usize> = motion
        .sub_blocks
        .iter()
        .map(|range| {
            let travel = motion
                .camera_at(range.start as f64)
                .distance(&motion.camera_at((range.end - 1) as f64), half);
            let for_motion = (travel / config.max_sub_block_motion_px.max(1e-6)).ceil() as usize;
            for_motion.clamp(1, (range.len() / shortest).max(1))
        })
        .collect();
    motion.split_sub_blocks(
        |k, _| pieces[k],
        |m, _, r| m.camera_at((r.start + r.end - 1) as f64 / 2.0),
    );
}
