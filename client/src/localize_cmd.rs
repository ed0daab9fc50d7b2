//! `pntr localize`: send one frame to a server and print the answer.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pntr_dataset::{DatasetIndex, Role};
use pntr_eval::pose_error;
use pntr_service::decode::{decode_jpeg, decode_png16, decode_png_rgb, upright_size, Limits};
use pntr_service::proto::{self, LocalizeResponse};
use pntr_service::wire;
use serde_json::json;

use crate::remote::{ConnectArgs, Remote};

/// Arguments of `pntr localize`.
#[derive(clap::Args, Debug)]
pub struct LocalizeArgs {
    /// Where the server is, and how to authenticate.
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Colour image: PNG or JPEG.
    #[arg(long, requires = "depth", conflicts_with = "dataset")]
    pub rgb: Option<PathBuf>,
    /// Depth image: 16-bit PNG in millimetres (0 = missing; see --depth-scale), or raw
    /// little-endian float32 metres (`.f32`, the size of the colour image).
    #[arg(long, requires = "rgb")]
    pub depth: Option<PathBuf>,
    /// Units per metre of a 16-bit depth PNG [default: 1000 (millimetres), or 5000 for a PNG in a
    /// TUM RGB-D folder (beside depth.txt)].
    #[arg(long, value_name = "UNITS_PER_M", requires = "depth")]
    pub depth_scale: Option<f64>,
    /// Camera intrinsics `fx,fy,cx,cy` in pixels, optionally followed by lens distortion
    /// `k1,k2,p1,p2[,k3]` (OpenCV / ROS plumb_bob). Default: the HPointLoc camera (256x256 frames
    /// only), or the dataset's camera with `--dataset`. Spaces work as separators too.
    #[arg(
        long,
        value_name = "FX,FY,CX,CY[,K1,K2,P1,P2,K3]",
        num_args = 1..=9,
        allow_negative_numbers = true
    )]
    pub intrinsics: Option<Vec<String>>,
    /// Dataset root, to send one of its query frames (with the ground truth printed beside the answer).
    #[arg(long, requires_all = ["scene", "query"])]
    pub dataset: Option<PathBuf>,
    /// Scene of --dataset.
    #[arg(long)]
    pub scene: Option<String>,
    /// Query number within the scene (Points in order, their queries in order).
    #[arg(long)]
    pub query: Option<usize>,
    /// Depth from a separate depth camera: registered to the colour image here, before it is sent
    /// (a 16-bit PNG; the depth camera's intrinsics from `--depth-intrinsics`, else from a
    /// 7-Scenes `camera-intrinsics.txt` beside the depth file).
    #[command(flatten)]
    pub depth_camera: crate::recordings::DepthCameraArgs,
    /// Frame convention of the answer: `map` (the map's own frame and camera axes) or `ros` (z-up
    /// map frame, optical camera axes x right, y down, z forward) [default: the server's].
    #[arg(long, value_parser = ["map", "ros"])]
    pub frame_convention: Option<String>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

const LIMITS: Limits = Limits {
    max_width: 16384,
    max_height: 16384,
};

fn read(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).with_context(|| format!("reading {}", path.display()))
}

/// The units per metre of a 16-bit depth PNG: the caller's, else TUM's 5000 for a PNG in a TUM
/// folder (`<seq>/depth/<stamp>.png` beside `<seq>/depth.txt`), else millimetres.
fn depth_units(depth: &Path, given: Option<f64>) -> Result<f64> {
    if let Some(u) = given {
        if !(u.is_finite() && u > 0.0) {
            bail!("--depth-scale {u}: give the depth PNG's units per metre (1000 for millimetres, 5000 for TUM)");
        }
        return Ok(u);
    }
    let tum = depth
        .parent()
        .and_then(Path::parent)
        .is_some_and(|seq| seq.join("depth.txt").is_file());
    if tum {
        eprintln!(
            "note: {} is in a TUM RGB-D folder: read at TUM's 5000 units per metre (--depth-scale overrides)",
            depth.display()
        );
        return Ok(5000.0);
    }
    Ok(1000.0)
}

/// A separate depth camera's image (`depth`, metres, the depth file's own pixels) registered to
/// the colour camera `colour` of a `w` x `h` image ([`pntr_dataset::depth_camera::register_depth`]):
/// the depth camera is `given` (`--depth-intrinsics`, `--depth-to-colour`), its intrinsics else
/// from a 7-Scenes `camera-intrinsics.txt` beside the depth file.
///
/// Errors: no colour camera, no depth intrinsics, or a depth image of another size than the depth
/// camera's; each names the file or the flag.
fn registered(
    depth: &Path,
    map: &pntr_core::DepthMap,
    given: &crate::recordings::DepthCameraOptions,
    colour: Option<&proto::Intrinsics>,
    (w, h): (u32, u32),
) -> Result<pntr_core::DepthMap> {
    use pntr_dataset::sevenscenes::{camera_intrinsics, CAMERA_INTRINSICS};
    let Some(colour) = colour else {
        bail!("registering the depth to the colour image needs the colour camera: give --intrinsics fx,fy,cx,cy");
    };
    let colour = pntr_service::decode::intrinsics(Some(colour), w, h)
        .map_err(|s| anyhow::anyhow!("--intrinsics: {}", s.message()))?;
    let size = (map.width, map.height);
    let k = match given.0 {
        Some([fx, fy, cx, cy]) => pntr_core::Intrinsics {
            fx,
            fy,
            cx,
            cy,
            width: size.0,
            height: size.1,
            distortion: [0.0; 5],
        },
        None => {
            let file = depth.with_file_name(CAMERA_INTRINSICS);
            if !file.is_file() {
                bail!(
                    "{}: registering it needs the depth camera's intrinsics: give --depth-intrinsics fx,fy,cx,cy, or put the recording's {CAMERA_INTRINSICS} beside it",
                    depth.display()
                );
            }
            camera_intrinsics(&file, size)?
        }
    };
    let camera = pntr_dataset::depth_camera::DepthCamera {
        intrinsics: k,
        colour_from_depth: given.1.unwrap_or_else(nalgebra::Isometry3::identity),
    };
    pntr_dataset::depth_camera::register_depth(map, &camera, &colour)
        .map_err(|e| anyhow::anyhow!("{}: {e}", depth.display()))
}

/// A request from image files, checked here so that a bad file is named before anything is sent;
/// with a separate depth camera (`depth_camera`, when one is given), the depth registered to the
/// colour camera (`colour`) first.
fn request_from_files(
    rgb: &Path,
    depth: &Path,
    depth_scale: Option<f64>,
    depth_camera: Option<&crate::recordings::DepthCameraOptions>,
    colour: Option<&proto::Intrinsics>,
) -> Result<proto::LocalizeRequest> {
    let bytes = read(rgb)?;
    let ext = |p: &Path| {
        p.extension()
            .map(|e| e.to_string_lossy().to_lowercase())
            .unwrap_or_default()
    };
    let (w, h, encoding) = match ext(rgb).as_str() {
        "png" => {
            let (w, h, _) = decode_png_rgb(&bytes, &LIMITS)
                .map_err(|s| anyhow::anyhow!("{}: {}", rgb.display(), s.message()))?;
            (w, h, proto::ImageEncoding::Png)
        }
        "jpg" | "jpeg" => {
            let (w, h, _, orientation) = decode_jpeg(&bytes, &LIMITS)
                .map_err(|s| anyhow::anyhow!("{}: {}", rgb.display(), s.message()))?;
            // The server applies the EXIF orientation; the depth must match the upright size.
            let (w, h) = upright_size(w, h, orientation);
            (w, h, proto::ImageEncoding::Jpeg)
        }
        other => bail!(
            "{}: unknown colour format `.{other}` (png, jpg)",
            rgb.display()
        ),
    };
    let mut dbytes = read(depth)?;
    let (dw, dh, dencoding) = match ext(depth).as_str() {
        "png" => {
            let (dw, dh, mm) = decode_png16(&dbytes, &LIMITS)
                .map_err(|s| anyhow::anyhow!("{}: {}", depth.display(), s.message()))?;
            let units = depth_units(depth, depth_scale)?;
            // Metres at those units; the likely unit mistakes are named before anything is sent.
            let metres: Vec<f32> = mm.iter().map(|v| v * (1000.0 / units) as f32).collect();
            let map = pntr_core::DepthMap {
                width: dw,
                height: dh,
                data: metres.clone(),
            };
            if let Some(hint) = pntr_dataset::recording::depth_unit_hint(&map, Some(units)) {
                bail!("{}: {hint}", depth.display());
            }
            if let Some(given) = depth_camera {
                let r = registered(depth, &map, given, colour, (w, h))?;
                dbytes = r.data.iter().flat_map(|m| m.to_le_bytes()).collect();
                (w, h, proto::DepthEncoding::Float32Meters)
            } else if units == 1000.0 {
                (dw, dh, proto::DepthEncoding::Png16Millimeters)
            } else {
                dbytes = metres.iter().flat_map(|m| m.to_le_bytes()).collect();
                (dw, dh, proto::DepthEncoding::Float32Meters)
            }
        }
        "f32" if depth_camera.is_some() => bail!(
            "{}: a separate depth camera's image is registered from a 16-bit PNG (give the depth camera's own PNG, or depth already registered without --depth-intrinsics and --depth-to-colour)",
            depth.display()
        ),
        "f32" => {
            if dbytes.len() != (w * h * 4) as usize {
                bail!(
                    "{}: {} bytes are not {w}x{h} float32 depths (the colour image's size)",
                    depth.display(),
                    dbytes.len()
                );
            }
            (w, h, proto::DepthEncoding::Float32Meters)
        }
        other => bail!(
            "{}: unknown depth format `.{other}` (png, f32)",
            depth.display()
        ),
    };
    Ok(proto::LocalizeRequest {
        rgb: Some(proto::Image {
            // Taken from the file (a JPEG's declared size is before its EXIF rotation).
            width: 0,
            height: 0,
            encoding: encoding as i32,
            data: bytes,
        }),
        depth: Some(proto::Depth {
            width: dw,
            height: dh,
            encoding: dencoding as i32,
            data: dbytes,
        }),
        ..Default::default()
    })
}

fn print(r: &LocalizeResponse, truth: Option<(f64, f64, String)>, as_json: bool) -> Result<()> {
    let status = proto::Status::try_from(r.status)
        .map(|s| s.as_str_name())
        .unwrap_or("UNKNOWN");
    let pose = wire::pose(r.pose.as_ref());
    let timings: serde_json::Map<String, serde_json::Value> = r
        .timings
        .iter()
        .map(|t| (t.stage.clone(), json!(1e3 * t.seconds)))
        .collect();
    if as_json {
        let mut v = json!({
            "status": status,
            "confidence": r.confidence,
            "min_confidence": r.min_confidence,
            "covariance": (r.covariance.len() == 36).then_some(&r.covariance),
            "inliers": r.inliers,
            "matched_image_id": r.matched_image_id,
            "map_id": r.map_id,
            "map_version": r.map_version,
            "reason": r.reason,
            "cause": wire::cause_label(r.cause),
            "stage_ms": timings,
            "frame_convention": wire::convention_name(r.frame_convention),
            "pose": pose.map(|p| {
                json!({"translation": [p.translation.x, p.translation.y, p.translation.z],
                       "rotation_wxyz": pntr_core::pose::canonical_wxyz(&p.rotation)})
            }),
        });
        if let Some((dt, dr, id)) = &truth {
            v["ground_truth"] =
                json!({"query_id": id, "translation_error_m": dt, "rotation_error_deg": dr});
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let matched = if r.matched_image_id.is_empty() {
        String::new()
    } else {
        format!(", matched {}", r.matched_image_id)
    };
    println!(
        "status {status} (map {} version {}), confidence {:.3} (threshold {:.2}), {} inliers{matched}",
        r.map_id, r.map_version, r.confidence, r.min_confidence, r.inliers
    );
    if !r.reason.is_empty() {
        println!("reason ({}): {}", wire::cause_label(r.cause), r.reason);
    }
    if let Some(p) = pose {
        let [w, x, y, z] = pntr_core::pose::canonical_wxyz(&p.rotation);
        let what = if r.frame_convention == proto::FrameConvention::Ros as i32 {
            "map_from_camera_optical (ROS: z up, optical camera axes)"
        } else {
            "world_from_camera (the map's own frame and camera axes)"
        };
        println!(
            "{what}: translation [{:.4}, {:.4}, {:.4}] m, rotation (w,x,y,z) [{w:.5}, {x:.5}, {y:.5}, {z:.5}]",
            p.translation.x, p.translation.y, p.translation.z
        );
    }
    if r.covariance.len() == 36 {
        let sd = |i: usize| r.covariance[i * 7].max(0.0).sqrt();
        println!(
            "standard deviation (from the covariance): position x {:.3} y {:.3} z {:.3} m, rotation x {:.2} y {:.2} z {:.2} deg",
            sd(0), sd(1), sd(2), sd(3).to_degrees(), sd(4).to_degrees(), sd(5).to_degrees()
        );
    }
    if let Some((dt, dr, id)) = truth {
        println!("against the ground truth of {id}: {dt:.3} m, {dr:.2} deg");
    }
    let t: Vec<String> = r
        .timings
        .iter()
        .map(|t| format!("{} {:.1}", t.stage, 1e3 * t.seconds))
        .collect();
    println!("ms: {}", t.join(", "));
    let matching = r.timings.iter().find(|t| t.stage == "matching");
    if matching.is_some_and(|t| t.seconds * 1e3 < 0.05) {
        println!("{}", pntr_eval::MATCHING_NOTE);
    }
    Ok(())
}

/// `pntr localize`.
pub fn run(args: &LocalizeArgs) -> Result<()> {
    let given = args.depth_camera.depth_camera()?;
    let depth_camera = (given.0.is_some() || given.1.is_some()).then_some(&given);
    let colour = match &args.intrinsics {
        Some(k) => Some(crate::recordings::parse_intrinsics(k)?),
        None => None,
    };
    if depth_camera.is_some() && args.dataset.is_some() {
        bail!("--depth-intrinsics and --depth-to-colour are for image files (--rgb, --depth): a dataset's depth is registered already");
    }
    let (mut req, truth) = match (&args.rgb, &args.depth, &args.dataset) {
        (Some(rgb), Some(depth), None) => (
            request_from_files(rgb, depth, args.depth_scale, depth_camera, colour.as_ref())?,
            None,
        ),
        (None, None, Some(root)) => {
            let index = DatasetIndex::open(root)?;
            let scene = index.scene(args.scene.as_deref().unwrap_or_default())?;
            let k = args.query.unwrap_or(0);
            let mut left = k;
            let mut found = None;
            for p in &scene.points {
                let r = p.open()?;
                let n = r.count(Role::Query);
                if left < n {
                    found = Some((p.query_id(left), r.view(Role::Query, left)?));
                    break;
                }
                left -= n;
            }
            let Some((id, v)) = found else {
                let total = k - left;
                bail!(
                    "--query {k} is out of range: scene {} has {total} queries (0..{})",
                    scene.name,
                    total.saturating_sub(1)
                );
            };
            (
                wire::raw_request(&v.rgb, &v.depth, Some(&v.intrinsics)),
                Some((id, v.world_from_camera)),
            )
        }
        _ => bail!("give --rgb and --depth, or --dataset, --scene and --query"),
    };
    if let Some(k) = colour {
        req.intrinsics = Some(k);
    } else if args.rgb.is_some() {
        let size = (req.depth.as_ref().map(|d| (d.width, d.height))).unwrap_or_default();
        if size != (256, 256) {
            bail!(
                "the frame is {}x{}: give its camera with --intrinsics fx,fy,cx,cy (the HPointLoc camera is the default only for 256x256 frames)",
                size.0,
                size.1
            );
        }
    }
    if let Some(c) = &args.frame_convention {
        req.frame_convention = pntr_service::config::parse_frame_convention(c)? as i32;
    }
    let mut remote = Remote::connect(&args.connect)?;
    let r = remote
        .send(req)
        .map_err(|s| crate::remote::call_error(&args.connect, &s))?;
    let truth = match (truth, wire::pose(r.pose.as_ref())) {
        (Some((id, gt)), Some(est)) if r.status == proto::Status::Localized as i32 => {
            // The answer is in the map's camera axes (optical for a map built from a recording),
            // or in ROS conventions; the dataset's truth in the map frame with Habitat's axes.
            let frames = remote.map_frames();
            let est = if r.frame_convention == proto::FrameConvention::Ros as i32 {
                pntr_core::pose::ros_to_map(&est, frames.up, frames.camera)
            } else {
                est
            };
            let est = pntr_core::convert_axes(&est, frames.camera, pntr_core::CameraAxes::Habitat);
            let (dt, dr) = pose_error(&est, &gt, false);
            Some((dt, dr, id))
        }
        _ => None,
    };
    print(&r, truth, args.json)
}
