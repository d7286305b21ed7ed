//! `bench long`: `quantacolor reconstruct` (default settings, this very binary, one child
//! process per run so that each run's peak memory is its own) on long recordings: 10,000 and
//! 100,000 frames of hand shake, 100,000 frames in which the camera jumps nine times, and
//! 1,000,000 frames (and the jumps capture's first part alone, the base its jumps are measured
//! against). For each: seconds, microseconds per frame, peak resident set, the ratio to
//! the 10,000-frame time of the same run, and sRGB PSNR against the ground truth.
//!
//! The captures are simulated once, streamed to disk ([`simulate_to_dir`]), into a cache
//! folder (`--work`) and reused while their description (a `.toml` stamp beside each) is
//! unchanged. The jumps capture is ten captures concatenated frame by frame, streamed too.

#![forbid(unsafe_code)]

use super::markdown::source_commit;
use crate::os_usage::{free_bytes, wait_with_usage};
use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use quantacolor::capture::npy::NpyHeader;
use quantacolor::capture::{io, Capture, CaptureWriter, FRAMES_FILE, GROUND_TRUTH_FILE};
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::progress::Progress;
use quantacolor::simulate::{simulate_to_dir, FluxSpec, MotionConfig, Scene, SimulationConfig};
use std::fmt::Write as _;
use std::fs::{self, File};
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

/// Options of `quantacolor bench long`.
#[derive(Debug, Clone, Args)]
pub struct LongArgs {
    /// Scene: an image file (PNG/JPEG sRGB, EXR linear; e.g.
    /// ../shared/data/scenes/kodim04.png) or builtin:chart.
    #[arg(long, default_value = "builtin:chart")]
    pub scene: String,
    /// Cache folder of the simulated captures and the reconstructions [default:
    /// quantacolor-bench-long in the system's temporary folder].
    #[arg(long)]
    pub work: Option<PathBuf>,
    /// Cases to run, comma-separated [default: all but those --skip-million leaves out].
    #[arg(long, value_enum, value_delimiter = ',')]
    pub cases: Vec<LongCase>,
    /// Leave out the 1,000,000-frame case (about 16 GB of disk at 496x254 and an hour of
    /// simulation on 2 cores the first time).
    #[arg(long)]
    pub skip_million: bool,
    /// Frames of the shortest case; the others have 10 times (natural, jumps) and 100 times as
    /// many.
    #[arg(long, default_value_t = 10_000)]
    pub frames_base: usize,
    /// Sensor size WIDTHxHEIGHT (the colour SPAD's CFA, cropped when smaller).
    #[arg(long, default_value = "496x254")]
    pub size: String,
    /// Seed of the simulations (the jumps capture's parts use this seed and the next nine).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Also write the table as Markdown to this file (the table of docs/speed.md).
    #[arg(long)]
    pub markdown: Option<PathBuf>,
}

/// The cases of `bench long`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, ValueEnum)]
pub enum LongCase {
    /// 10,000 frames (--frames-base) of hand shake.
    #[value(name = "10k")]
    Base,
    /// The first 10,000-frame part of the jumps capture on its own: the base of its ratio.
    #[value(name = "10k-jumps-first")]
    JumpsFirst,
    /// 100,000 frames of hand shake.
    #[value(name = "100k")]
    Natural,
    /// 100,000 frames: ten 10,000-frame captures of stronger hand shake, concatenated.
    #[value(name = "100k-jumps")]
    Jumps,
    /// 1,000,000 frames: the 100,000-frame capture ten times over (simulating a million
    /// frames of their own would take an hour on 2 cores; time and memory are what this case
    /// measures, and its PSNR is that of the photons of the 100,000).
    #[value(name = "1m")]
    Million,
}

/// Copies of the 100,000-frame capture in the 1,000,000-frame one.
const MILLION_PARTS: usize = 10;

/// Parts of the jumps capture (and jumps: one fewer).
const JUMP_PARTS: usize = 10;
/// Peak translation of the jumps capture's hand shake, px (the default hand shake's is 4).
const JUMP_AMPLITUDE_PX: f64 = 8.0;
/// Hand-shake cycles per [`SHAKE_FRAMES`] frames: the default hand shake of a 10,000-frame
/// capture (0.75 cycles over the burst) at the same speed in every case, i.e. the same
/// physical tremor whatever the length of the recording.
const SHAKE_CYCLES: f64 = 0.75;
const SHAKE_FRAMES: f64 = 10_000.0;
/// Light level, mean detections per W pixel per frame (the quality benchmark's).
const FLUX: f64 = 0.1;
/// Scoring: the quality benchmark's protocol (border, 99.5th-percentile normalisation).
const BORDER_PX: usize = 16;
/// Disk kept free beyond the captures' own size, bytes.
const DISK_MARGIN: u64 = 1 << 30;
/// Version of the cached captures' description: bump when the simulation changes.
const CACHE_VERSION: u32 = 1;

/// One case: what it is and where its capture lies.
struct Case {
    case: LongCase,
    label: String,
    frames: usize,
    capture: PathBuf,
    /// Simulations that make the capture: one, or the jumps capture's parts.
    parts: Vec<SimulationConfig>,
}

/// One measured case.
struct Measured {
    label: String,
    frames: usize,
    seconds: f64,
    peak_rss_bytes: u64,
    psnr_srgb: f64,
}

/// Runs `quantacolor bench long`.
pub(super) fn long(args: &LongArgs, progress: &dyn Progress) -> Result<()> {
    if args.frames_base < 2 {
        bail!("--frames-base must be at least 2, got {}", args.frames_base);
    }
    let (width, height) = crate::cmd_simulate::parse_size(&args.size)?;
    let scene = Scene::from_spec(&args.scene).with_context(|| format!("--scene {}", args.scene))?;
    let scene_id = scene_identity(&args.scene);
    let work = args
        .work
        .clone()
        .unwrap_or_else(|| std::env::temp_dir().join("quantacolor-bench-long"));
    fs::create_dir_all(&work)
        .with_context(|| format!("cannot create --work {}", work.display()))?;
    let cases = plan(args, width, height, &work, &scene_id)?;
    check_disk(&cases, &work, &scene_id)?;
    // Captures of one simulation each, which a concatenated case may use as its parts.
    let singles: Vec<(&SimulationConfig, &Path)> = cases
        .iter()
        .filter_map(|c| match c.parts.as_slice() {
            [config] => Some((config, c.capture.as_path())),
            _ => None,
        })
        .collect();
    for case in &cases {
        make_capture(case, &singles, &scene, &scene_id, &work, progress).with_context(|| {
            format!(
                "making the {} capture {}",
                case.label,
                case.capture.display()
            )
        })?;
    }
    let exe = std::env::current_exe().context("cannot find the quantacolor executable")?;
    let mut rows = Vec::with_capacity(cases.len());
    for case in &cases {
        eprintln!("reconstructing {} ({} frames)", case.label, case.frames);
        rows.push(measure(&exe, case, &work)?);
    }
    let base_s = cases
        .iter()
        .zip(&rows)
        .find(|(c, _)| c.case == LongCase::Base)
        .map(|(_, r)| r.seconds);
    let table = table(&rows, base_s, args.frames_base)?;
    print!("{table}");
    if let Some(path) = &args.markdown {
        let md = markdown(args, width, height, &table)?;
        quantacolor::atomic::write_atomic_synced(path, |w| w.write_all(md.as_bytes()))?;
    }
    Ok(())
}

/// The scene as cached captures record it: the canonical path of a file, or the built-in name.
fn scene_identity(spec: &str) -> String {
    fs::canonicalize(spec).map_or_else(|_| spec.to_string(), |p| p.display().to_string())
}

/// A file-name-safe tag of the scene (its file stem or built-in name).
fn scene_tag(spec: &str) -> String {
    let stem = Path::new(spec.trim_start_matches("builtin:"))
        .file_stem()
        .map_or_else(|| "scene".into(), |s| s.to_string_lossy().to_string());
    stem.chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
        .collect()
}

/// The simulation of `frames` frames of hand shake of peak `amplitude_px` with `seed`.
fn shake_config(
    width: usize,
    height: usize,
    frames: usize,
    amplitude_px: f64,
    seed: u64,
) -> SimulationConfig {
    SimulationConfig {
        height,
        width,
        frames,
        cfa: "colorspad".into(),
        flux: FluxSpec::Mean { flux: FLUX },
        motion: MotionConfig::Handheld {
            amplitude_px,
            rotation_deg: 0.5,
            cycles: SHAKE_CYCLES * frames as f64 / SHAKE_FRAMES,
        },
        seed,
        ..SimulationConfig::default()
    }
}

/// The cases asked for, in order, with their captures' places and simulations.
fn plan(
    args: &LongArgs,
    width: usize,
    height: usize,
    work: &Path,
    scene_id: &str,
) -> Result<Vec<Case>> {
    let mut wanted = if args.cases.is_empty() {
        LongCase::value_variants().to_vec()
    } else {
        args.cases.clone()
    };
    if args.skip_million {
        wanted.retain(|&c| c != LongCase::Million);
    }
    wanted.sort();
    wanted.dedup();
    if wanted.is_empty() {
        bail!("no case left to run (--cases and --skip-million)");
    }
    let base = args.frames_base;
    let scale = |k: usize| {
        base.checked_mul(k)
            .with_context(|| format!("--frames-base {base} times {k} overflows"))
    };
    let tag = format!("{}-{width}x{height}-s{}", scene_tag(scene_id), args.seed);
    let natural = |frames: usize| shake_config(width, height, frames, 4.0, args.seed);
    // Part k of the jumps capture: another hand and other photons, the same sensor (hot
    // pixels).
    let jump_part = |k: u64| SimulationConfig {
        dark_seed: Some(args.seed),
        ..shake_config(width, height, base, JUMP_AMPLITUDE_PX, args.seed + k)
    };
    wanted
        .into_iter()
        .map(|case| {
            let (label, frames, parts) = match case {
                LongCase::Base => ("natural".to_string(), base, vec![natural(base)]),
                LongCase::Natural => ("natural".into(), scale(10)?, vec![natural(scale(10)?)]),
                LongCase::JumpsFirst => ("the jumps' first part".into(), base, vec![jump_part(0)]),
                LongCase::Jumps => {
                    let parts = (0..JUMP_PARTS as u64).map(jump_part).collect();
                    (
                        format!("{JUMP_PARTS} parts ({} jumps)", JUMP_PARTS - 1),
                        scale(JUMP_PARTS)?,
                        parts,
                    )
                }
                LongCase::Million => (
                    format!(
                        "the {} repeated {MILLION_PARTS} times",
                        thousands(scale(10)?)
                    ),
                    scale(100)?,
                    vec![natural(scale(10)?); MILLION_PARTS],
                ),
            };
            let kind = match case {
                LongCase::Jumps => "jumps",
                LongCase::JumpsFirst => "jumps-first",
                LongCase::Million => "repeated",
                LongCase::Base | LongCase::Natural => "natural",
            };
            Ok(Case {
                case,
                label: format!("{} frames, {label}", thousands(frames)),
                frames,
                capture: work.join(format!("{tag}-{kind}-{frames}")),
                parts,
            })
        })
        .collect()
}

/// `n` with commas between thousands (1,000,000).
fn thousands(n: usize) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// The description of a simulated capture that its cache stamp records.
fn stamp_text(scene_id: &str, config: &SimulationConfig) -> Result<String> {
    Ok(format!(
        "cache_version = {CACHE_VERSION}\nscene = {scene_id:?}\n{}",
        toml::to_string(config)?
    ))
}

/// The cache stamp of `capture`: a `.toml` beside it.
fn stamp_path(capture: &Path) -> PathBuf {
    capture.with_extension("toml")
}

/// Whether `capture` is complete and was made from `text` (its stamp).
fn cached(capture: &Path, text: &str, frames: usize) -> bool {
    let stamp_ok = fs::read_to_string(stamp_path(capture)).is_ok_and(|s| s == text);
    stamp_ok
        && capture.join(GROUND_TRUTH_FILE).is_file()
        && Capture::open(capture).is_ok_and(|c| c.frames.frame_count() == frames)
}

/// The stamp of a case's capture (every part's description).
fn case_stamp(case: &Case, scene_id: &str) -> Result<String> {
    case.parts
        .iter()
        .map(|p| stamp_text(scene_id, p))
        .collect::<Result<Vec<_>>>()
        .map(|texts| texts.join("\n# next part\n"))
}

/// Bytes of the frames of `frames` packed frames of the capture size.
fn capture_bytes(config: &SimulationConfig, frames: usize) -> u64 {
    (frames * config.height * config.width.div_ceil(8)) as u64
}

/// Fails with a clear message when the captures still to be made do not fit on the disk.
fn check_disk(cases: &[Case], work: &Path, scene_id: &str) -> Result<()> {
    let mut needed = 0u64;
    for case in cases {
        if cached(&case.capture, &case_stamp(case, scene_id)?, case.frames) {
            continue;
        }
        needed += capture_bytes(&case.parts[0], case.frames);
        if case.parts.len() > 1 {
            // The parts are kept beside the concatenation (each distinct one once).
            for (k, part) in case.parts.iter().enumerate() {
                if !case.parts[..k].contains(part) {
                    needed += capture_bytes(part, part.frames);
                }
            }
        }
    }
    if needed == 0 {
        return Ok(());
    }
    let free = free_bytes(work)?;
    if free < needed + DISK_MARGIN {
        bail!(
            "the captures still to simulate need {:.1} GB in {} (plus {:.1} GB kept free), but \
             only {:.1} GB is free; give --work on a larger disk, or leave out the longest case \
             (--skip-million) or others (--cases)",
            needed as f64 / 1e9,
            work.display(),
            DISK_MARGIN as f64 / 1e9,
            free as f64 / 1e9
        );
    }
    Ok(())
}

/// Simulates (or finds in the cache) the capture of `case`; a part described as one of
/// `singles` (the captures of single-simulation cases) is that capture.
fn make_capture(
    case: &Case,
    singles: &[(&SimulationConfig, &Path)],
    scene: &Scene,
    scene_id: &str,
    work: &Path,
    progress: &dyn Progress,
) -> Result<()> {
    let stamp = case_stamp(case, scene_id)?;
    if cached(&case.capture, &stamp, case.frames) {
        eprintln!("reusing {}", case.capture.display());
        return Ok(());
    }
    match case.parts.as_slice() {
        [config] => simulate_cached(config, scene, scene_id, &case.capture, progress)?,
        parts => {
            let name = case
                .capture
                .file_name()
                .context("capture path without a name")?
                .to_string_lossy()
                .to_string();
            let mut dirs: Vec<PathBuf> = Vec::with_capacity(parts.len());
            for (k, config) in parts.iter().enumerate() {
                // A part made before from the same description is used again: an earlier
                // part, or the capture of a case of its own (made before, cases run in order).
                if let Some(same) = parts[..k].iter().position(|p| p == config) {
                    dirs.push(dirs[same].clone());
                    continue;
                }
                if let Some((_, dir)) = singles.iter().find(|(single, _)| *single == config) {
                    dirs.push(dir.to_path_buf());
                    continue;
                }
                let dir = work.join("parts").join(format!("{name}-part{k}"));
                simulate_cached(config, scene, scene_id, &dir, progress)?;
                dirs.push(dir);
            }
            concatenate(&dirs, &case.capture, progress)?;
        }
    }
    quantacolor::atomic::write_atomic(stamp_path(&case.capture), |w| {
        w.write_all(stamp.as_bytes())
    })?;
    Ok(())
}

/// Simulates `config` into `dir` unless its cached copy is complete and current.
fn simulate_cached(
    config: &SimulationConfig,
    scene: &Scene,
    scene_id: &str,
    dir: &Path,
    progress: &dyn Progress,
) -> Result<()> {
    let stamp = stamp_text(scene_id, config)?;
    if cached(dir, &stamp, config.frames) {
        return Ok(());
    }
    eprintln!("simulating {} frames into {}", config.frames, dir.display());
    // A stale stamp must not vouch for the new capture if this one is interrupted.
    let _ = fs::remove_file(stamp_path(dir));
    simulate_to_dir(config, scene, dir, progress)?;
    quantacolor::atomic::write_atomic(stamp_path(dir), |w| w.write_all(stamp.as_bytes()))?;
    Ok(())
}

/// Writes the captures `parts` one after the other as the capture `out`, a frame at a time:
/// the first part's CFA, metadata (reference frame), hot pixels and ground truth, the frames of
/// all, and a `[concatenated]` table naming the parts in `capture.toml`.
fn concatenate(parts: &[PathBuf], out: &Path, progress: &dyn Progress) -> Result<()> {
    let first = Capture::open(&parts[0])?;
    let (h, w) = (first.cfa.height(), first.cfa.width());
    let mut counts = Vec::with_capacity(parts.len());
    for dir in parts {
        let c = Capture::open(dir)?;
        if (c.cfa.height(), c.cfa.width()) != (h, w) || c.frames.is_multibit() {
            bail!(
                "{} is not a binary capture of {w}x{h} like {}",
                dir.display(),
                parts[0].display()
            );
        }
        counts.push(c.frames.frame_count());
    }
    let total: usize = counts.iter().sum();
    eprintln!(
        "concatenating {} captures into {}",
        parts.len(),
        out.display()
    );
    let _ = fs::remove_file(stamp_path(out));
    let mut writer = CaptureWriter::create(out, total, h, w)?;
    let mut frame = vec![0u8; writer.frame_bytes()];
    progress.start("concatenating", total as u64);
    for (dir, &count) in parts.iter().zip(&counts) {
        let path = dir.join(FRAMES_FILE);
        let mut file =
            File::open(&path).with_context(|| format!("cannot open {}", path.display()))?;
        let mut head = vec![0u8; 4096];
        let n = file
            .read(&mut head)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let header =
            NpyHeader::parse(&head[..n]).map_err(|m| anyhow::anyhow!("{}: {m}", path.display()))?;
        file.seek(SeekFrom::Start(header.data_offset as u64))
            .with_context(|| format!("cannot read {}", path.display()))?;
        let mut reader = std::io::BufReader::with_capacity(1 << 22, file);
        for _ in 0..count {
            reader
                .read_exact(&mut frame)
                .with_context(|| format!("cannot read {}", path.display()))?;
            writer.write_frame(&frame)?;
            progress.advance(1);
        }
    }
    progress.finish();
    let truth = io::read_npy_3d::<f32>(parts[0].join(GROUND_TRUTH_FILE))?;
    writer.write_ground_truth(&truth)?;
    let mut table = toml::Table::new();
    table.insert(
        "parts".into(),
        parts
            .iter()
            .map(|p| toml::Value::from(p.display().to_string()))
            .collect::<Vec<_>>()
            .into(),
    );
    table.insert(
        "note".into(),
        "the parts' frames one after another; the ground truth, hot pixels and reference frame \
         are the first part's"
            .into(),
    );
    let mut extra = toml::Table::new();
    extra.insert("concatenated".into(), toml::Value::Table(table));
    writer.finish(
        &first.cfa,
        &first.meta,
        first.hot_pixels.as_ref(),
        Some(&extra),
    )?;
    Ok(())
}

/// Runs `quantacolor reconstruct` on the case's capture as a child process and scores its
/// output.
fn measure(exe: &Path, case: &Case, work: &Path) -> Result<Measured> {
    let out = work.join("reconstructions").join(
        case.capture
            .file_name()
            .context("capture path without a name")?,
    );
    let log_path = out.with_extension("log");
    if let Some(parent) = log_path.parent() {
        fs::create_dir_all(parent)
            .with_context(|| format!("cannot create {}", parent.display()))?;
    }
    let log =
        File::create(&log_path).with_context(|| format!("cannot create {}", log_path.display()))?;
    let start = Instant::now();
    let child = Command::new(exe)
        .arg("reconstruct")
        .arg(&case.capture)
        .arg("--out")
        .arg(&out)
        .arg("--overwrite") // the benchmark's own reconstruction of the case, run again
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .with_context(|| format!("cannot run {}", exe.display()))?;
    let usage = wait_with_usage(child)?;
    let seconds = start.elapsed().as_secs_f64();
    if !usage.status.success() {
        let text = fs::read_to_string(&log_path).unwrap_or_default();
        bail!(
            "quantacolor reconstruct {} failed ({}): {}",
            case.capture.display(),
            usage.status,
            text.trim()
        );
    }
    let estimate = io::read_npy_3d::<f32>(out.join("linear.npy"))?;
    let truth = io::read_npy_3d::<f32>(case.capture.join(GROUND_TRUTH_FILE))?;
    let (h, w, _) = truth.dim();
    let opts = EvalOptions {
        border: BORDER_PX.min(h.min(w) / 4),
        normalize_percentile: Some(99.5),
    };
    let scores = evaluate(estimate.view(), truth.view(), &opts)?;
    Ok(Measured {
        label: case.label.clone(),
        frames: case.frames,
        seconds,
        peak_rss_bytes: usage.peak_rss_bytes,
        psnr_srgb: scores.psnr_srgb,
    })
}

/// The results as a Markdown table (also what stdout shows).
fn table(rows: &[Measured], base_s: Option<f64>, base_frames: usize) -> Result<String> {
    let mut t = String::new();
    writeln!(
        t,
        "| case | time (s) | µs per frame | peak RSS (MB) | time / {}-frame time | sRGB PSNR (dB) |",
        thousands(base_frames)
    )?;
    writeln!(t, "|---|---|---|---|---|---|")?;
    for r in rows {
        let ratio = base_s.map_or("–".to_string(), |b| format!("{:.2}x", r.seconds / b));
        writeln!(
            t,
            "| {} | {:.2} | {:.1} | {:.0} | {ratio} | {:.2} |",
            r.label,
            r.seconds,
            r.seconds * 1e6 / r.frames as f64,
            r.peak_rss_bytes as f64 / 1e6,
            r.psnr_srgb
        )?;
    }
    Ok(t)
}

/// The command line that reproduces the table (the options that change it).
fn command_line(args: &LongArgs) -> String {
    let mut c = format!("quantacolor bench long --scene {}", args.scene);
    if !args.cases.is_empty() {
        let names: Vec<String> = args
            .cases
            .iter()
            .filter_map(|k| k.to_possible_value().map(|v| v.get_name().to_string()))
            .collect();
        c += &format!(" --cases {}", names.join(","));
    }
    if args.skip_million {
        c += " --skip-million";
    }
    if args.frames_base != 10_000 {
        c += &format!(" --frames-base {}", args.frames_base);
    }
    if args.size != "496x254" {
        c += &format!(" --size {}", args.size);
    }
    if args.seed != 1 {
        c += &format!(" --seed {}", args.seed);
    }
    c
}

/// The Markdown file: how the table was made, then the table.
fn markdown(args: &LongArgs, width: usize, height: usize, table: &str) -> Result<String> {
    let mut md = String::new();
    writeln!(
        md,
        "Generated by `{}` at {} on {} threads: `quantacolor reconstruct` with default \
         settings, one child process per case, on simulated {width}x{height} SPAD captures \
         (colour-SPAD CFA, {FLUX} detections per W pixel per frame, hand shake at the speed of \
         the default 10,000-frame hand shake). Peak RSS is the child's own (`wait4`, or its \
         sampled `VmHWM` when that is below this process's peak); PSNR is sRGB against the \
         simulator's ground truth ({BORDER_PX} px border excluded, 99.5th-percentile \
         normalisation).\n",
        command_line(args),
        source_commit(),
        rayon::current_num_threads()
    )?;
    md.push_str(table);
    Ok(md)
}
