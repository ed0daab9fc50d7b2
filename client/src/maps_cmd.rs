//! `pntr maps`: administer the maps of a running pntr-server (`pntr.v1.MapAdmin`): list, load,
//! replace, unload and reload them without a restart.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use pntr_service::proto::map_admin_client::MapAdminClient;
use pntr_service::proto::{self, MapChange};
use pntr_service::tokio;
use pntr_service::tonic::transport::Channel;

use crate::remote::{self, ConnectArgs};

/// How to reach the server's admin API.
#[derive(Args, Debug, Clone)]
pub struct AdminConnect {
    /// Server address, HOST:PORT (or a URL).
    #[arg(long)]
    pub addr: String,
    /// The server's admin token (`pntr-server --admin-token`; not the clients' token), or
    /// PNTR_ADMIN_TOKEN.
    #[arg(long, env = "PNTR_ADMIN_TOKEN", hide_env_values = true)]
    pub admin_token: Option<String>,
    /// PEM file of the CA that signed the server's certificate: connect with TLS.
    #[arg(long)]
    pub tls_ca: Option<PathBuf>,
    /// Name to verify in the server's certificate (default: the host of --addr).
    #[arg(long)]
    pub tls_domain: Option<String>,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `pntr maps ...`.
#[derive(Subcommand, Debug)]
pub enum MapsCommand {
    /// List the maps the server holds: id, version, images, file.
    List {
        #[command(flatten)]
        connect: AdminConnect,
    },
    /// Load a map file (a path on the server; a relative one is resolved against the server's working
    /// folder) under the id its header gives.
    Load {
        #[command(flatten)]
        connect: AdminConnect,
        /// The map file, as a path on the server's file system.
        #[arg(long)]
        file: String,
    },
    /// Replace a loaded map by a new file of the same map id, atomically: frames being localized
    /// finish on the old map, later ones use the new one.
    Replace {
        #[command(flatten)]
        connect: AdminConnect,
        /// The loaded map to replace.
        #[arg(long)]
        map_id: String,
        /// The new map file, as a path on the server's file system.
        #[arg(long)]
        file: String,
    },
    /// Stop serving a map.
    Unload {
        #[command(flatten)]
        connect: AdminConnect,
        /// The map to unload.
        #[arg(long)]
        map_id: String,
    },
    /// Add recordings on the server (poses in the map's frame) to a loaded map: new keyframes only,
    /// the map's file rewritten atomically as a new version, then served as `replace` does.
    Extend {
        #[command(flatten)]
        connect: AdminConnect,
        /// The loaded map to extend.
        #[arg(long)]
        map_id: String,
        /// A recording on the server's file system: TUM RGB-D folder, rosbag2 folder or .mcap file
        /// (repeat for several).
        #[arg(long, required = true)]
        sequence: Vec<String>,
        /// A TUM trajectory on the server for each --sequence (the map frame's poses of the camera).
        #[arg(long)]
        trajectory: Vec<String>,
        /// Units per metre of integer depth, when the recording's format says otherwise.
        #[arg(long)]
        depth_scale: Option<f64>,
        /// ROS 2 bag: the colour topic (sensor_msgs/Image, or its `/compressed` sibling)
        /// [default on the server: /camera/color/image_raw].
        #[arg(long)]
        rgb_topic: Option<String>,
        /// ROS 2 bag: the depth topic aligned to the colour camera (or its `/compressedDepth`
        /// sibling) [default on the server: /camera/aligned_depth_to_color/image_raw].
        #[arg(long)]
        depth_topic: Option<String>,
        /// ROS 2 bag: the colour camera's sensor_msgs/CameraInfo topic [default on the server:
        /// /camera/color/camera_info].
        #[arg(long)]
        info_topic: Option<String>,
        /// ROS 2 bag: poses from this topic instead of TF (geometry_msgs/PoseStamped of the optical
        /// frame, or nav_msgs/Odometry of the body).
        #[arg(long)]
        pose_topic: Option<String>,
        /// ROS 2 bag: the world frame of TF poses [default on the server: map].
        #[arg(long)]
        map_frame: Option<String>,
        /// ROS 2 bag: the camera's optical frame in TF (default: the colour images' frame_id).
        #[arg(long)]
        camera_frame: Option<String>,
    },
    /// Read every loaded map's file again and replace those that changed (what SIGHUP does).
    Reload {
        #[command(flatten)]
        connect: AdminConnect,
    },
    /// Join two map files of one building whose poses are in different frames (two SLAM sessions
    /// that started elsewhere), offline: B's keyframes are localized in A, the rigid transform from
    /// B's frame to A's is estimated from the verified ones that agree (refused when too few do),
    /// and one map in A's frame with both sessions' images is written (atomically).
    Merge(MergeArgs),
}

/// Arguments of `pntr maps merge`.
#[derive(Args, Debug)]
pub struct MergeArgs {
    /// The map whose frame, id, preset and codebook the result keeps.
    pub a: PathBuf,
    /// The map joined into it.
    pub b: PathBuf,
    /// The merged map file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// B's keyframes tried, evenly spaced (0: all).
    #[arg(long, default_value_t = 300)]
    pub keyframes: usize,
    /// Fewest agreeing keyframes for a transform (at least 4; and at least 5% of those tried
    /// must agree whatever this says).
    #[arg(long, default_value_t = 6)]
    pub min_support: usize,
    /// A recording whose poses are in A's frame (the merged map's; the one A was built from, or a
    /// later drive localized in it): the merged map's own calibration is fitted on its frames that
    /// are not map images, as `pntr calibrate --db OUT --sequence` would. Repeat it for several.
    /// Without it the merged map keeps A's calibration, reported stale (it was fitted on A's
    /// images alone).
    #[arg(long, value_name = "DIR|FILE.mcap")]
    pub sequence: Vec<PathBuf>,
    /// Poses of a `--sequence` from this TUM trajectory file instead of the recording's own (one
    /// per `--sequence`, in the same order).
    #[arg(long, value_name = "FILE.txt")]
    pub trajectory: Vec<PathBuf>,
    /// The camera of the `--sequence` recordings as `fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]`, replacing
    /// their own calibration.
    #[arg(long, value_name = "FX,FY,CX,CY")]
    pub intrinsics: Option<String>,
    /// Depth units per metre of the `--sequence` recordings, replacing what their format says.
    #[arg(long, value_name = "UNITS_PER_M")]
    pub depth_scale: Option<f64>,
    /// ROS 2 bag topics of a `--sequence`.
    #[command(flatten)]
    pub topics: crate::recordings::TopicArgs,
    /// Frames of the `--sequence` recordings the calibration is fitted on, evenly spaced (0: all);
    /// each is localized twice.
    #[arg(long, default_value_t = pntr_mapping::recording_map::SELF_CALIBRATION_FRAMES, value_name = "N")]
    pub self_calibration_frames: usize,
    /// Folder of the ONNX models (for the calibration's fit); default: found as `pntr build-db`
    /// finds it.
    #[arg(long)]
    pub models: Option<PathBuf>,
    /// Threads for ONNX Runtime.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Print JSON: transform (translation, rotation_wxyz: B's map frame into A's), covariance (36
    /// values, ROS order, A's frame), supporting_keyframes, keyframes_tried, keyframes_verified,
    /// images, rms_m, seconds, file, calibration (as `pntr build-db --json` gives it) and
    /// calibration_refit (frames, seconds, kept_because; null without `--sequence`).
    #[arg(long)]
    pub json: bool,
}

/// `pntr maps merge`.
fn merge(args: &MergeArgs) -> Result<()> {
    use pntr_mapping::merge::{run, MergeParams, Refit};
    let a = crate::loading::load_map(&args.a, args.threads)
        .with_context(|| format!("reading map A {}", args.a.display()))?;
    let b = crate::loading::load_map(&args.b, args.threads)
        .with_context(|| format!("reading map B {}", args.b.display()))?;
    if args.min_support < pntr_mapping::merge::MIN_SUPPORT_FLOOR {
        anyhow::bail!(
            "--min-support {}: at least {} agreeing keyframes are needed (fewer agree by chance between different buildings)",
            args.min_support,
            pntr_mapping::merge::MIN_SUPPORT_FLOOR
        );
    }
    let params = MergeParams {
        keyframes: args.keyframes,
        min_support: args.min_support,
        ..MergeParams::default()
    };
    if !args.trajectory.is_empty() && args.trajectory.len() != args.sequence.len() {
        anyhow::bail!(
            "--trajectory given {} times for {} --sequence: give one per sequence, in the same order",
            args.trajectory.len(),
            args.sequence.len()
        );
    }
    let recordings = args
        .sequence
        .iter()
        .enumerate()
        .map(|(i, p)| {
            crate::recordings::open_recording(
                p,
                args.trajectory.get(i).map(PathBuf::as_path),
                &args.topics,
                args.depth_scale,
                args.intrinsics.as_deref(),
            )
        })
        .collect::<Result<Vec<_>>>()?;
    let sessions = crate::recordings::as_sessions(&recordings);
    let refit = (!sessions.is_empty()).then(|| Refit {
        sessions: &sessions,
        fit: pntr_mapping::own_calibration::FitOptions {
            keep_on_refusal: false,
            ..pntr_mapping::own_calibration::FitOptions::shipped(args.self_calibration_frames)
        },
    });
    let models = crate::loading::models_dir(args.models.as_deref())?;
    let t = std::time::Instant::now();
    let (merged, r) = run(
        a,
        &b,
        &params,
        refit,
        &crate::loading::stages(&models, args.threads),
        &mut crate::output::bars(),
    )
    .with_context(|| {
        format!(
            "merging {} into {} (nothing was written to {})",
            args.b.display(),
            args.a.display(),
            args.out.display()
        )
    })?;
    let seconds = t.elapsed().as_secs_f64();
    pntr_pipeline::mapfile::save(&merged, &args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let stale = merged.calibration_is_stale();
    if stale {
        eprintln!(
            "warning: the merged map keeps A's own calibration, fitted on A's images alone (stale): give --sequence with a recording in A's frame to fit one for the merged map"
        );
    }
    let tr = r.a_from_b.translation.vector;
    let q = r.a_from_b.rotation;
    if args.json {
        println!(
            "{}",
            serde_json::json!({
                "transform": {
                    "translation": [tr.x, tr.y, tr.z],
                    "rotation_wxyz": [q.w, q.i, q.j, q.k],
                },
                "covariance": r.covariance,
                "supporting_keyframes": r.supporting_keyframes,
                "keyframes_tried": r.keyframes_tried,
                "keyframes_verified": r.keyframes_verified,
                "images": r.images,
                "rms_m": r.rms_m,
                "seconds": seconds,
                "file": args.out.display().to_string(),
                "calibration": crate::own_calibration::summary(merged.header.calibration.as_ref(), stale),
                "calibration_refit": r.calibration_refit,
            })
        );
        return Ok(());
    }
    let sd = |i: usize| r.covariance[i * 7].max(0.0).sqrt();
    println!(
        "B's frame into A's: translation ({:.3}, {:.3}, {:.3}) m, rotation {:.2} deg about ({:.3}, {:.3}, {:.3}); standard error {:.1} mm, {:.2} deg",
        tr.x,
        tr.y,
        tr.z,
        q.angle().to_degrees(),
        q.axis().map_or(0.0, |a| a.x),
        q.axis().map_or(0.0, |a| a.y),
        q.axis().map_or(1.0, |a| a.z),
        1e3 * (sd(0).powi(2) + sd(1).powi(2) + sd(2).powi(2)).sqrt(),
        (sd(3).powi(2) + sd(4).powi(2) + sd(5).powi(2)).sqrt().to_degrees()
    );
    println!(
        "{} of {} keyframes tried agree ({} localized in A); refit RMS {:.3} m; {} images written to {} in {:.1} s",
        r.supporting_keyframes,
        r.keyframes_tried,
        r.keyframes_verified,
        r.rms_m,
        r.images,
        args.out.display(),
        seconds
    );
    println!(
        "{}",
        crate::own_calibration::line(merged.header.calibration.as_ref(), stale)
    );
    Ok(())
}

async fn client(c: &AdminConnect) -> Result<MapAdminClient<Channel>> {
    let ch = remote::channel(&connect_args(c)).await?;
    Ok(MapAdminClient::new(ch))
}

fn connect_args(c: &AdminConnect) -> ConnectArgs {
    ConnectArgs {
        addr: c.addr.clone(),
        token: c.admin_token.clone(),
        tls_ca: c.tls_ca.clone(),
        tls_domain: c.tls_domain.clone(),
        ..ConnectArgs::default()
    }
}

fn request<T>(c: &AdminConnect, message: T) -> Result<pntr_service::tonic::Request<T>> {
    if c.admin_token.is_none() {
        anyhow::bail!("no admin token: give --admin-token or set PNTR_ADMIN_TOKEN (the server's --admin-token)");
    }
    remote::authorized(&connect_args(c), message)
}

fn refused(s: pntr_service::tonic::Status) -> anyhow::Error {
    anyhow::anyhow!(
        "the server refused: {} ({})",
        s.message(),
        pntr_service::service::code_name(s.code())
    )
}

fn entry_json(m: &proto::LoadedMap) -> serde_json::Value {
    serde_json::json!({
        "map_id": m.map_id,
        "version": m.version,
        "images": m.images,
        "file": m.file,
        "preset": m.preset,
        "built_at": m.built_at,
        "heap_bytes": m.heap_bytes,
        "calibration": m.calibration.as_ref().map(remote::calibration_json),
    })
}

fn change_json(c: &MapChange) -> serde_json::Value {
    serde_json::json!({
        "map": c.map.as_ref().map(entry_json),
        "previous_version": c.previous_version,
        "same_frame": c.same_frame,
        "load_seconds": c.load_seconds,
        "images_added": c.images_added,
    })
}

fn print_change(what: &str, c: &MapChange, json: bool) {
    if json {
        println!("{}", change_json(c));
        return;
    }
    let Some(m) = &c.map else {
        println!("{what}");
        return;
    };
    print!(
        "{what} `{}` version {} ({} images, preset {}, {})",
        m.map_id, m.version, m.images, m.preset, m.file
    );
    if !c.previous_version.is_empty() {
        print!(
            "; replaced version {}; {}",
            c.previous_version,
            if c.same_frame {
                "same frame: open streams keep their track"
            } else {
                "another frame: open streams start afresh"
            }
        );
    }
    if c.load_seconds > 0.0 {
        print!("; prepared in {:.1} s", c.load_seconds);
    }
    println!();
}

/// `pntr maps`.
pub fn run(cmd: &MapsCommand) -> Result<()> {
    if let MapsCommand::Merge(args) = cmd {
        return merge(args);
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    rt.block_on(async {
        match cmd {
            MapsCommand::List { connect } => {
                let maps = client(connect)
                    .await?
                    .list_maps(request(connect, proto::ListMapsRequest {})?)
                    .await
                    .map_err(refused)?
                    .into_inner()
                    .maps;
                if connect.json {
                    let list: Vec<_> = maps.iter().map(entry_json).collect();
                    println!("{}", serde_json::json!({ "maps": list }));
                } else if maps.is_empty() {
                    println!("no maps loaded");
                } else {
                    for m in &maps {
                        let calibration = m.calibration.as_ref().map_or(String::new(), |c| {
                            let stale = if c.stale { ", STALE" } else { "" };
                            format!("  calibration {} {:.3}{stale}", c.source, c.threshold)
                        });
                        println!(
                            "{}  version {}  {} images  preset {}  {}{calibration}",
                            m.map_id, m.version, m.images, m.preset, m.file
                        );
                    }
                }
            }
            MapsCommand::Load { connect, file } => {
                let c = client(connect)
                    .await?
                    .load_map(request(
                        connect,
                        proto::LoadMapRequest { file: file.clone() },
                    )?)
                    .await
                    .map_err(refused)?
                    .into_inner();
                print_change("loaded", &c, connect.json);
            }
            MapsCommand::Replace {
                connect,
                map_id,
                file,
            } => {
                let c = client(connect)
                    .await?
                    .replace_map(request(
                        connect,
                        proto::ReplaceMapRequest {
                            map_id: map_id.clone(),
                            file: file.clone(),
                        },
                    )?)
                    .await
                    .map_err(refused)?
                    .into_inner();
                print_change("serving", &c, connect.json);
            }
            MapsCommand::Extend {
                connect,
                map_id,
                sequence,
                trajectory,
                depth_scale,
                rgb_topic,
                depth_topic,
                info_topic,
                pose_topic,
                map_frame,
                camera_frame,
            } => {
                let given = |v: &Option<String>| v.clone().unwrap_or_default();
                let c = client(connect)
                    .await?
                    .extend_map(request(
                        connect,
                        proto::ExtendMapRequest {
                            map_id: map_id.clone(),
                            sequence: sequence.clone(),
                            trajectory: trajectory.clone(),
                            depth_scale: depth_scale.unwrap_or(0.0),
                            rgb_topic: given(rgb_topic),
                            depth_topic: given(depth_topic),
                            info_topic: given(info_topic),
                            pose_topic: given(pose_topic),
                            map_frame: given(map_frame),
                            camera_frame: given(camera_frame),
                        },
                    )?)
                    .await
                    .map_err(refused)?
                    .into_inner();
                if !connect.json {
                    print!("added {} images; ", c.images_added);
                }
                print_change("serving", &c, connect.json);
            }
            MapsCommand::Unload { connect, map_id } => {
                let c = client(connect)
                    .await?
                    .unload_map(request(
                        connect,
                        proto::UnloadMapRequest {
                            map_id: map_id.clone(),
                        },
                    )?)
                    .await
                    .map_err(refused)?
                    .into_inner();
                print_change("unloaded", &c, connect.json);
            }
            MapsCommand::Reload { connect } => {
                let r = client(connect)
                    .await?
                    .reload_maps(request(connect, proto::ReloadMapsRequest {})?)
                    .await
                    .map_err(refused)?
                    .into_inner();
                if connect.json {
                    let reloaded: Vec<_> = r.reloaded.iter().map(change_json).collect();
                    println!(
                        "{}",
                        serde_json::json!({
                            "reloaded": reloaded,
                            "unchanged_map_ids": r.unchanged_map_ids,
                            "failed": r.failed,
                        })
                    );
                } else {
                    for c in &r.reloaded {
                        print_change("reloaded", c, false);
                    }
                    for id in &r.unchanged_map_ids {
                        println!("unchanged `{id}`");
                    }
                    for f in &r.failed {
                        println!("failed {f}");
                    }
                }
                if !connect.json
                    && r.reloaded.is_empty()
                    && r.unchanged_map_ids.is_empty()
                    && r.failed.is_empty()
                {
                    println!("no maps loaded");
                }
                if !r.failed.is_empty() {
                    anyhow::bail!(
                        "{} map(s) could not be reloaded and keep their loaded version",
                        r.failed.len()
                    );
                }
            }
            MapsCommand::Merge(_) => unreachable!("merged offline above"),
        }
        Ok(())
    })
}
