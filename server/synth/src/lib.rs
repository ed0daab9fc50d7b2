//! Synthetic HPointLoc: procedural apartments rendered to RGB-D under HPointLoc's protocol and written
//! in its exact on-disk layout.
//!
//! Why it exists: the real dataset is not downloadable here, and every test, benchmark and demo of
//! pntr must run on data made on the spot. The generator follows the protocol to the letter (2 m grid
//! of key positions in free space, camera at 1.25 m, six database views at yaw 0..300 step 60,
//! queries within 0.5 m with random yaw, 256x256 at 90 degrees, planar depth clipped at 10 m, sensor
//! noise of 0.02) so that code written against these files runs unchanged on the real ones.
//!
//! How: [`scene`] builds an apartment of axis-aligned boxes (rooms split with doors, furniture,
//! pictures, windows) with procedural [`texture`]s; [`protocol`] places the cameras; [`render`] ray
//! casts each view. Points render in parallel (rayon), each into its own file; everything is a pure
//! function of the seed, so a dataset is reproducible bit for bit.

pub mod effects;
pub mod protocol;
pub mod render;
pub mod scene;
pub mod texture;
pub mod trajectory;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use pntr_core::Intrinsics;
use pntr_dataset::{layout, write_point, DatasetError, PointRecord, View, WriteOptions};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

pub use protocol::PointPlan;
pub use render::{Frame, Renderer};
pub use scene::{Scene, SceneOptions};
pub use texture::TextureImage;

/// What to generate.
#[derive(Debug, Clone)]
pub struct SynthConfig {
    /// Number of scenes (apartments).
    pub scenes: usize,
    /// Points (key positions) per scene.
    pub points_per_scene: usize,
    /// Query poses drawn per Point (some are discarded when not in free space).
    pub queries_per_point: usize,
    /// Seed of everything.
    pub seed: u64,
    /// Standard deviation of query pitch and roll, degrees.
    pub tilt_sigma_deg: f64,
    /// Extra image textures.
    pub textures: Vec<Arc<TextureImage>>,
    /// How files are written.
    pub write: WriteOptions,
    /// Camera of the database views (HPointLoc's 256x256, 90 degrees by default).
    pub db_camera: Intrinsics,
    /// Camera of the queries (the database camera by default): a robot's camera against a map
    /// made with another.
    pub query_camera: Intrinsics,
    /// Also render, per scene, a robot's drive of this many seconds ([`trajectory`]: 0.5 m/s,
    /// 10 Hz, through the query camera) into `sequences/<scene>/` in the TUM RGB-D layout.
    pub trajectory_seconds: Option<f64>,
    /// The drive is a mapping run ([`trajectory::plan_mapping_run`]: every reachable Point once, a full circle
    /// at each, then stop); `trajectory_seconds` caps it.
    pub mapping_run: bool,
    /// Another route through the same scene ([`trajectory::plan_drive_on`]); `None`: the default.
    pub route_seed: Option<u64>,
    /// A robot's captures instead of clean renders for queries and drives (`synth --realism`):
    /// other lighting and camera effects; database views stay clean.
    pub realism: Option<effects::Realism>,
    /// Each apartment beside an exact copy of itself, joined by a door ([`scene::twin`]): the
    /// database views, queries and mapping runs cover the original half only, other drives go to
    /// the Points of both halves, so a map of the original and a drive into the copy make a stream
    /// that leaves its map into look-alike rooms.
    pub twin: bool,
}

impl Default for SynthConfig {
    /// One Val-sized scene: 23 Points, 50 queries drawn per Point.
    fn default() -> Self {
        Self {
            scenes: 1,
            points_per_scene: 23,
            queries_per_point: 50,
            seed: 0,
            tilt_sigma_deg: 2.0,
            textures: Vec::new(),
            write: WriteOptions::default(),
            db_camera: Intrinsics::hpointloc(),
            query_camera: Intrinsics::hpointloc(),
            trajectory_seconds: None,
            mapping_run: false,
            route_seed: None,
            realism: None,
            twin: false,
        }
    }
}

/// What was generated for one scene.
#[derive(Debug, Clone)]
pub struct SceneSummary {
    /// Scene name.
    pub name: String,
    /// Number of Points.
    pub points: usize,
    /// Number of database views.
    pub db_views: usize,
    /// Number of queries kept.
    pub queries: usize,
    /// Number of query poses discarded (not in free space).
    pub discarded_queries: usize,
    /// Number of rooms.
    pub rooms: usize,
    /// Number of boxes in the scene geometry.
    pub boxes: usize,
    /// Apartment size (x, z), metres.
    pub size_m: (f32, f32),
    /// Frames of the drive written to `sequences/<scene>/` (0 without `trajectory_seconds`).
    pub sequence_frames: usize,
    /// For a mapping run, the seconds the whole run takes (every reachable Point visited and turned at):
    /// more than `trajectory_seconds` means the drive was cut before it covered the apartment.
    pub mapping_run_seconds: Option<f64>,
    /// Indices of the Points no drive reaches, ascending ([`trajectory::unreachable_points`]: rooms
    /// the furniture closes off at the robot's clearance); a drive or mapping run leaves them out.
    pub unreachable_points: Vec<usize>,
    /// With [`SynthConfig::twin`]: how far along +x the copy lies from the original (the original's
    /// width, metres): a pose in the copy minus this is its look-alike in the original.
    pub twin_offset_m: Option<f32>,
}

/// What a synthesis run produced.
#[derive(Debug, Clone)]
pub struct Summary {
    /// Per scene.
    pub scenes: Vec<SceneSummary>,
    /// Frames rendered and written.
    pub frames: u64,
    /// Wall-clock time of the whole run, seconds.
    pub seconds: f64,
    /// The dataset root (holding `HPointLoc_dataset`).
    pub root: PathBuf,
}

/// Errors of a synthesis run.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// Writing the dataset failed.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// A file-system operation failed.
    #[error("{path}: {source}")]
    Io {
        /// The path.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The configuration cannot be honoured.
    #[error("invalid synth configuration: {0}")]
    Config(String),
}

/// The name of scene `i` of a run.
pub fn scene_name(i: usize) -> String {
    format!("synth{i:03}")
}

/// A generated scene with its planned Points.
pub struct PlannedScene {
    /// The geometry.
    pub scene: Scene,
    /// The Points, in file order.
    pub points: Vec<PointPlan>,
    /// With [`SynthConfig::twin`]: the Points of the copy (the original's moved by the door's
    /// `at_x`, with no views planned), which drives visit and nothing renders, and the door.
    pub twin: Option<(Vec<PointPlan>, scene::TwinDoor)>,
}

/// Generate scene `index` of `cfg` and plan its Points. Grows the apartment until the 2 m grid holds
/// `points_per_scene` key positions in free space, then keeps that many.
pub fn plan_scene(cfg: &SynthConfig, index: usize) -> PlannedScene {
    let mut rng =
        ChaCha8Rng::seed_from_u64(cfg.seed ^ (index as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
    let opts = SceneOptions {
        images: cfg.textures.clone(),
    };
    // About 4 m^2 of floor per grid node, plus room for walls and furniture.
    let mut area = (cfg.points_per_scene as f32 * 4.0 * 1.45).max(12.0);
    loop {
        let scene = scene::generate(&scene_name(index), &mut rng, area, &opts);
        let obstacles = scene.obstacles();
        let keys = protocol::key_positions(&scene, &obstacles, &mut rng);
        if keys.len() >= cfg.points_per_scene {
            let keys = protocol::choose_points(keys, cfg.points_per_scene, &mut rng);
            let points = keys
                .into_iter()
                .map(|k| {
                    protocol::plan_point(
                        k,
                        &scene,
                        &obstacles,
                        cfg.queries_per_point,
                        cfg.tilt_sigma_deg,
                        &mut rng,
                    )
                })
                .collect();
            if !cfg.twin {
                return PlannedScene {
                    scene,
                    points,
                    twin: None,
                };
            }
            if let Some((doubled, door)) = scene::twin(&scene) {
                let copies = points
                    .iter()
                    .map(|p: &PointPlan| PointPlan {
                        key_xz: (p.key_xz.0 + door.at_x as f64, p.key_xz.1),
                        db: Vec::new(),
                        queries: Vec::new(),
                        discarded: 0,
                    })
                    .collect();
                return PlannedScene {
                    scene: doubled,
                    points,
                    twin: Some((copies, door)),
                };
            }
        }
        area *= 1.15;
    }
}

fn frame_seed(seed: u64, scene: usize, point: usize, view: usize) -> u64 {
    seed.wrapping_mul(0x2545_f491_4f6c_dd1d)
        ^ ((scene as u64) << 40)
        ^ ((point as u64) << 20)
        ^ view as u64
}

/// Render one capture: the clean render, or with `realism` a robot's (its lighting, then its frame
/// effects). `scene` is (run seed, scene index), `seed` the frame's own; `drive` is the frame's index
/// in a recording, whose lighting and exposure drift smoothly from frame to frame instead of being
/// drawn for each.
fn capture_frame(
    renderer: &Renderer,
    pose: &nalgebra::Isometry3<f64>,
    k: &Intrinsics,
    scene: (u64, usize),
    seed: u64,
    realism: Option<&effects::Realism>,
    drive: Option<usize>,
) -> Frame {
    let Some(realism) = realism else {
        return renderer.render(pose, k, seed);
    };
    let scene_seed = scene.0 ^ (scene.1 as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    let (lighting, look) = match drive {
        Some(i) => {
            let base = scene_seed ^ 0x0d71_5e00;
            (
                realism.drifting_lighting(renderer.scene(), scene_seed, base, i),
                realism.effects.drifting_look(base, i),
            )
        }
        None => (
            realism.lighting_of(renderer.scene(), scene_seed, seed),
            realism.effects.look(seed),
        ),
    };
    let mut f = renderer.render_lit(pose, k, seed, &lighting);
    realism
        .effects
        .apply_with(&mut f.rgb, &mut f.depth, &look, seed);
    f
}

/// Render every view of one Point: database views through `cameras.0`, queries through `cameras.1`
/// (as a robot's captures with `realism`).
pub fn render_point(
    renderer: &Renderer,
    plan: &PointPlan,
    cameras: (&Intrinsics, &Intrinsics),
    seeds: (u64, usize, usize),
    realism: Option<&effects::Realism>,
    on_frame: &(dyn Fn() + Sync),
) -> PointRecord {
    let view = |pose: &nalgebra::Isometry3<f64>, k: &Intrinsics, i: usize, capture: bool| {
        let f = capture_frame(
            renderer,
            pose,
            k,
            (seeds.0, seeds.1),
            frame_seed(seeds.0, seeds.1, seeds.2, i),
            realism.filter(|_| capture),
            None,
        );
        on_frame();
        View {
            world_from_camera: *pose,
            rgb: f.rgb,
            depth: f.depth,
            semantic: Some(f.labels),
            intrinsics: *k,
        }
    };
    let db = plan
        .db
        .iter()
        .enumerate()
        .map(|(i, p)| view(p, cameras.0, i, false))
        .collect();
    let queries = plan
        .queries
        .iter()
        .enumerate()
        .map(|(i, p)| view(p, cameras.1, 1000 + i, true))
        .collect();
    PointRecord {
        db,
        queries,
        instance_categories: None,
    }
}

/// Total frames a run will render (for progress bars).
pub fn planned_frames(planned: &[PlannedScene]) -> u64 {
    planned
        .iter()
        .flat_map(|s| s.points.iter())
        .map(|p| (p.db.len() + p.queries.len()) as u64)
        .sum()
}

/// Generate, render and write a dataset under `root` (files go to `root/HPointLoc_dataset/<scene>/`).
///
/// Each scene is written into a temporary folder and moved into place when complete; an existing
/// scene folder of the same name is replaced only then, so an interrupted run leaves the old data.
/// `on_frame` is called after every rendered frame (from worker threads).
pub fn synthesize(
    cfg: &SynthConfig,
    root: &Path,
    planned: Vec<PlannedScene>,
    on_frame: &(dyn Fn() + Sync),
) -> Result<Summary, SynthError> {
    if cfg.points_per_scene == 0 || cfg.scenes == 0 {
        return Err(SynthError::Config(
            "scenes and points per scene must be at least 1".into(),
        ));
    }
    for (what, k) in [("database", &cfg.db_camera), ("query", &cfg.query_camera)] {
        k.validate()
            .map_err(|e| SynthError::Config(format!("{what} camera: {e}")))?;
    }
    let start = Instant::now();
    let cameras = (&cfg.db_camera, &cfg.query_camera);
    let frames = AtomicU64::new(0);
    let count = || {
        frames.fetch_add(1, Ordering::Relaxed);
        on_frame();
    };
    let base = root.join(layout::DATASET_DIR);
    std::fs::create_dir_all(&base).map_err(|source| SynthError::Io {
        path: base.clone(),
        source,
    })?;
    let mut summaries = Vec::new();
    for (si, ps) in planned.iter().enumerate() {
        let name = &ps.scene.name;
        let final_dir = base.join(name);
        let tmp_dir = base.join(format!(".{name}.partial-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&tmp_dir);
        let tmp_root = tmp_dir.clone();
        let renderer = Renderer::new(&ps.scene);
        let table = ps.scene.instance_categories.clone();
        ps.points
            .par_iter()
            .enumerate()
            .try_for_each(|(pi, plan)| {
                let mut rec = render_point(
                    &renderer,
                    plan,
                    cameras,
                    (cfg.seed, si, pi),
                    cfg.realism.as_ref(),
                    &count,
                );
                rec.instance_categories = Some(table.clone());
                let path = tmp_root.join(format!("{name}_point{pi}.hdf5"));
                write_point(&path, &rec, &cfg.write)
            })?;
        let old = base.join(format!(".{name}.old-{}", std::process::id()));
        if final_dir.exists() {
            std::fs::rename(&final_dir, &old).map_err(|source| SynthError::Io {
                path: final_dir.clone(),
                source,
            })?;
        }
        std::fs::rename(&tmp_dir, &final_dir).map_err(|source| SynthError::Io {
            path: final_dir.clone(),
            source,
        })?;
        let _ = std::fs::remove_dir_all(&old);
        let (sequence_frames, mapping_run_seconds) = match cfg.trajectory_seconds {
            Some(seconds) => render_drive(cfg, root, si, ps, &renderer, seconds, &count)?,
            None => (0, None),
        };
        summaries.push(SceneSummary {
            name: name.clone(),
            points: ps.points.len(),
            db_views: ps.points.iter().map(|p| p.db.len()).sum(),
            queries: ps.points.iter().map(|p| p.queries.len()).sum(),
            discarded_queries: ps.points.iter().map(|p| p.discarded).sum(),
            rooms: ps.scene.rooms.len(),
            boxes: ps.scene.boxes.len(),
            size_m: (ps.scene.width_m, ps.scene.depth_m),
            sequence_frames,
            mapping_run_seconds,
            unreachable_points: trajectory::unreachable_points(&ps.scene, &ps.points),
            twin_offset_m: ps.twin.as_ref().map(|(_, door)| door.at_x),
        });
    }
    Ok(Summary {
        scenes: summaries,
        frames: frames.load(Ordering::Relaxed),
        seconds: start.elapsed().as_secs_f64(),
        root: root.to_path_buf(),
    })
}

/// Folder of the sequences `synthesize` writes with `trajectory_seconds`: `root/sequences`.
pub const SEQUENCES_DIR: &str = "sequences";

/// Render the drive of scene `si` and write it to `root/sequences/<scene>/` (TUM layout); returns the
/// number of frames and, for a mapping run, the seconds the whole run takes uncapped.
fn render_drive(
    cfg: &SynthConfig,
    root: &Path,
    si: usize,
    ps: &PlannedScene,
    renderer: &Renderer,
    seconds: f64,
    on_frame: &(dyn Fn() + Sync),
) -> Result<(usize, Option<f64>), SynthError> {
    if !(seconds.is_finite() && seconds > 0.0) {
        return Err(SynthError::Config(format!(
            "trajectory seconds must be positive, not {seconds}"
        )));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(
        cfg.seed ^ 0x7472_616a ^ (si as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15),
    );
    let plan = if cfg.mapping_run {
        trajectory::plan_mapping_run
    } else {
        trajectory::plan_drive_on
    };
    // The whole mapping run, uncapped (planning only), to tell whether `seconds` cut it.
    let mapping_run_seconds = cfg.mapping_run.then(|| {
        let whole = trajectory::plan_mapping_run(
            &ps.scene,
            &ps.points,
            1e6,
            trajectory::DEFAULT_RATE_HZ,
            trajectory::DEFAULT_SPEED_MPS,
            &mut rng.clone(),
            cfg.route_seed,
        );
        whole.len() as f64 / trajectory::DEFAULT_RATE_HZ
    });
    // A drive (not a mapping run) of a twin apartment visits the copy's Points too.
    let driven: Vec<PointPlan> = match (&ps.twin, cfg.mapping_run) {
        (Some((copies, _)), false) => ps.points.iter().chain(copies).cloned().collect(),
        _ => ps.points.clone(),
    };
    let drive = plan(
        &ps.scene,
        &driven,
        seconds,
        trajectory::DEFAULT_RATE_HZ,
        trajectory::DEFAULT_SPEED_MPS,
        &mut rng,
        cfg.route_seed,
    );
    let frames: Vec<pntr_dataset::tum::SequenceFrame> = drive
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let f = capture_frame(
                renderer,
                &p.world_from_camera,
                &cfg.query_camera,
                (cfg.seed, si),
                frame_seed(cfg.seed, si, 1 << 19, i),
                cfg.realism.as_ref(),
                Some(i),
            );
            on_frame();
            pntr_dataset::tum::SequenceFrame {
                timestamp: p.t,
                rgb: f.rgb,
                depth: f.depth,
                // groundtruth.txt follows the TUM convention: optical camera axes.
                world_from_camera: pntr_core::convert_axes(
                    &p.world_from_camera,
                    pntr_core::CameraAxes::Habitat,
                    pntr_core::CameraAxes::OpenCv,
                ),
            }
        })
        .collect();
    let dir = root.join(SEQUENCES_DIR).join(&ps.scene.name);
    std::fs::create_dir_all(root.join(SEQUENCES_DIR)).map_err(|source| SynthError::Io {
        path: root.join(SEQUENCES_DIR),
        source,
    })?;
    pntr_dataset::tum::write_sequence(&dir, &frames, &cfg.query_camera)?;
    Ok((frames.len(), mapping_run_seconds))
}

/// Frames the drives of a run will render (for progress bars).
pub fn planned_sequence_frames(cfg: &SynthConfig) -> u64 {
    cfg.trajectory_seconds.map_or(0, |s| {
        cfg.scenes as u64 * (s * trajectory::DEFAULT_RATE_HZ).round().max(1.0) as u64
    })
}

/// Plan all scenes of `cfg` (cheap; no rendering).
pub fn plan_all(cfg: &SynthConfig) -> Vec<PlannedScene> {
    (0..cfg.scenes)
        .into_par_iter()
        .map(|i| plan_scene(cfg, i))
        .collect()
}

/// Load every PNG/JPEG image in `dir` as a texture.
pub fn load_textures(dir: &Path) -> Result<Vec<Arc<TextureImage>>, SynthError> {
    let io = |source| SynthError::Io {
        path: dir.to_path_buf(),
        source,
    };
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
        })
        .collect();
    paths.sort();
    let mut out = Vec::new();
    for p in paths {
        let img = image::open(&p)
            .map_err(|e| SynthError::Config(format!("{}: cannot decode image: {e}", p.display())))?
            .to_rgb8();
        let (width, height) = img.dimensions();
        if width == 0 || height == 0 {
            continue;
        }
        let data = img
            .pixels()
            .map(|px| {
                [
                    px[0] as f32 / 255.0,
                    px[1] as f32 / 255.0,
                    px[2] as f32 / 255.0,
                ]
            })
            .collect();
        out.push(Arc::new(TextureImage {
            width,
            height,
            data,
        }));
    }
    if out.is_empty() {
        return Err(SynthError::Config(format!(
            "{}: no PNG or JPEG images found",
            dir.display()
        )));
    }
    Ok(out)
}
