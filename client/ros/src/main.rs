//! pntr-ros: a ROS 2 node that localizes a robot's RGB-D camera with a running pntr-server.
//!
//! It joins the ROS 2 graph as a native DDS participant (ros2-client on RustDDS: no ROS
//! installation), subscribes to colour, depth, camera_info, /tf and /tf_static, sends the frames
//! through one gRPC `LocalizeStream` (so the server tracks the robot between them) at most `rate_hz`
//! a second, and publishes the base frame's pose (`pntr/pose`), `map -> odom` on /tf and
//! /diagnostics; the `pntr/relocalize` service (std_srvs/Trigger) drops the track. See
//! docs/robot-integration.md.

mod answer;
mod frames;
mod grpc;
mod msgs;
mod node;
mod params;
mod tf;

/// The pntr.v1 client generated from `proto/pntr/v1/localizer.proto`.
#[allow(missing_docs, clippy::all, clippy::pedantic)]
pub mod proto {
    tonic::include_proto!("pntr.v1");
}

use std::path::PathBuf;
use std::time::Duration;

use clap::Parser;

/// Command line (ROS 2 arguments follow `--ros-args`).
#[derive(Parser, Debug)]
#[command(
    name = "pntr-ros",
    version,
    about = "A ROS 2 node (no ROS installation needed) that localizes a robot's RGB-D camera with pntr-server",
    after_help = "ROS 2 arguments: --ros-args [-p name:=value]... [-r from:=to]... [-r __ns:=/NS] [-r __node:=NAME] [--params-file FILE.yaml]\n\
Parameters: rgb_topic, depth_topic, info_topic, map_frame, odom_frame, base_frame, rate_hz, pose_topic,\n\
relocalize_service, tf_publish_rate_hz, transform_tolerance_s, sync_slop_s, publish_tf (docs/robot-integration.md).\n\
Environment: ROS_DOMAIN_ID (default 0); RMW_IMPLEMENTATION (rmw_cyclonedds_cpp or rmw_fastrtps_cpp:\n\
the relocalize service in that RMW's wire format only; unset: both);\n\
PNTR_LOG (a tracing filter, e.g. pntr_ros=debug; --ros-args --log-level LEVEL overrides it)."
)]
struct Cli {
    /// The server, HOST:PORT.
    #[arg(long)]
    addr: String,
    /// The map to localize in (empty: the server's only map).
    #[arg(long, default_value = "")]
    map_id: String,
    /// Bearer token the server expects.
    #[arg(long, env = "PNTR_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// CA certificate (PEM) of a TLS server.
    #[arg(long)]
    tls_ca: Option<PathBuf>,
    /// The name in the server's certificate, when not the host of --addr.
    #[arg(long)]
    tls_domain: Option<String>,
    /// Seconds one frame may take before the stream is reopened.
    #[arg(long, default_value_t = 5.0)]
    answer_timeout_s: f64,
}

fn main() {
    let (own, ros) = params::split_args(std::env::args().collect());
    let cli = Cli::parse_from(own);
    let ros = match params::RosArgs::parse(&ros) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::exit(2);
        }
    };
    // ros2-client's check of ROS_DISTRO speaks of its own build features: not a user's concern.
    let quiet = "ros2_client::distributions=off";
    let filter = match (&ros.log_level, std::env::var("PNTR_LOG")) {
        (Some(level), _) => format!("pntr_ros={level},warn,{quiet}"),
        (None, Ok(f)) => format!("{f},{quiet}"),
        (None, Err(_)) => format!("pntr_ros=info,warn,{quiet}"),
    };
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::new(filter))
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr)
        .init();
    if cli.answer_timeout_s.is_nan() || cli.answer_timeout_s <= 0.0 {
        eprintln!("error: --answer-timeout-s must be > 0");
        std::process::exit(2);
    }
    let target = grpc::Target {
        addr: cli.addr,
        token: cli.token,
        tls_ca: cli.tls_ca,
        tls_domain: cli.tls_domain,
        answer_timeout: Duration::from_secs_f64(cli.answer_timeout_s),
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("tokio runtime");
    let code = runtime.block_on(async move {
        match node::run(ros, target, cli.map_id).await {
            Ok(()) => 0,
            Err(e) => {
                eprintln!("error: {e:#}");
                1
            }
        }
    });
    // The DDS threads are not joined: leave at once (SIGINT must end the node within seconds).
    std::process::exit(code);
}
