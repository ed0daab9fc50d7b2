//! `pntr`: the command-line face of pntr.
//!
//! The binary only parses arguments, wires library crates together and prints; all domain logic
//! lives in the server crates so that the service, the CLI and the tests share one implementation.
//! Output meant for other programs is JSON on stdout (`--json`); progress and logs go to stderr.

// One module per subcommand (`*_cmd`); they import only the shared modules below them, never
// each other.
mod bench_cmd;
mod build_cmd;
mod calibrate_cmd;
mod eval_cmd;
mod info_cmd;
mod localize_cmd;
mod maps_cmd;
mod register_cmd;
mod replay_cmd;
mod synth_cmd;

// Shared by the subcommands.
mod evaluation;
mod load;
mod loading;
mod output;
mod own_calibration;
mod plot;
mod recordings;
mod remote;
mod soak;

use std::path::PathBuf;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "pntr",
    version,
    about = "Indoor RGB-D localization (PNTR pipeline): tools"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Generate a synthetic dataset in the HPointLoc layout.
    Synth(synth_cmd::SynthArgs),
    /// Register 3D-3D correspondences from a CSV file and print the transform as JSON.
    Register(register_cmd::RegisterArgs),
    /// Build a map database from a dataset (--dataset) or a robot's recordings (--sequence), or add
    /// recordings to an existing map (--extend).
    BuildDb(build_cmd::BuildArgs),
    /// Evaluate the pipeline on a dataset's queries (HPointLoc recall table, JSON report).
    Eval(eval_cmd::EvalArgs),
    /// Fit the confidence calibration on a dataset the map covers and one or more it does not.
    Calibrate(calibrate_cmd::CalibrateArgs),
    /// Localize one frame (image files, or a dataset query) through a running pntr-server.
    Localize(localize_cmd::LocalizeArgs),
    /// Load-test a running pntr-server with a dataset's query frames.
    Bench(bench_cmd::BenchArgs),
    /// Stream a recorded drive (TUM RGB-D folder, ROS 2 bag or 7-Scenes folder) through a running pntr-server's
    /// LocalizeStream and measure the trajectory (ATE, RPE), the share localized and the latency.
    Replay(replay_cmd::ReplayArgs),
    /// List the scenes and Points of a dataset and check that every file reads, or describe a map
    /// file from its header (`--db`): preset, the models its images and its queries use, camera,
    /// scenes.
    Info {
        /// Dataset root (the folder holding HPointLoc_dataset, or that folder).
        #[arg(
            long,
            required_unless_present_any = ["db", "addr"],
            conflicts_with_all = ["db", "addr"]
        )]
        dataset: Option<PathBuf>,
        /// A map file (`pntr build-db`) to describe instead; only its header is read.
        #[arg(long)]
        db: Option<PathBuf>,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
        /// With `--db`: also list every map image (id, place, stamp, world_from_camera in the map's
        /// frame and axes; `image_list` in JSON) and the file's version. Reads the whole map.
        #[arg(long, requires = "db")]
        images: bool,
        /// Describe a map a running pntr-server serves instead (GetMapInfo: version, preset, camera,
        /// axes, the other maps it holds), HOST:PORT.
        #[arg(long, conflicts_with = "db")]
        addr: Option<String>,
        /// With `--addr`: the map (empty: the server's only map).
        #[arg(long, default_value = "", requires = "addr")]
        map_id: String,
        /// With `--addr`: the clients' bearer token, when the server wants one (or PNTR_TOKEN).
        #[arg(long, env = "PNTR_TOKEN", hide_env_values = true)]
        token: Option<String>,
        /// With `--addr`: PEM file of the CA that signed the server's certificate (TLS).
        #[arg(long, requires = "addr")]
        tls_ca: Option<PathBuf>,
        /// With `--tls-ca`: the name to verify in the server's certificate (default: the host of
        /// --addr).
        #[arg(long, requires = "tls_ca")]
        tls_domain: Option<String>,
    },
    /// Administer the maps of a running pntr-server without a restart: list, load, replace, unload,
    /// extend, reload (needs the server's admin token); and merge two map files offline.
    #[command(subcommand)]
    Maps(maps_cmd::MapsCommand),
    /// The main job on the embedded default: the demo scene and its map (made once, cached), served by
    /// an in-process pntr-server and queried over gRPC; prints the recall table and stage timings.
    Demo {
        /// Where to put the demo data.
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
        /// Folder of the ONNX models.
        /// (default: `PNTR_MODELS`, `./models`, next to the executable, `../share/pntr/models`).
        #[arg(long)]
        models: Option<PathBuf>,
        /// How many queries (evenly spaced) to localise.
        #[arg(long, default_value_t = 200)]
        queries: usize,
    },
}

/// Exit quietly, as other command-line tools do, when the reader of stdout goes away (`pntr ... |
/// head -1`): Rust ignores SIGPIPE, so `println!` to a closed pipe panics; that one panic becomes
/// exit status 141 (128 + SIGPIPE, what a shell reports for a tool killed by it) without a message.
/// SIGPIPE itself stays ignored, so a socket the server closed is an error, not a silent death.
fn quiet_on_closed_stdout() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let message = info
            .payload()
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| info.payload().downcast_ref::<&str>().copied())
            .unwrap_or("");
        if message.contains("failed printing to stdout") && message.contains("Broken pipe") {
            std::process::exit(141);
        }
        default(info);
    }));
}

fn main() {
    use std::io::IsTerminal;
    quiet_on_closed_stdout();
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .init();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Synth(args) => synth_cmd::run(&args),
        Command::Register(args) => register_cmd::run(&args),
        Command::BuildDb(args) => build_cmd::build_db(&args),
        Command::Localize(args) => localize_cmd::run(&args),
        Command::Bench(args) => bench_cmd::run(&args),
        Command::Replay(args) => replay_cmd::run(&args),
        Command::Eval(args) => eval_cmd::eval(&args),
        Command::Calibrate(args) => calibrate_cmd::run(&args),
        Command::Maps(cmd) => maps_cmd::run(&cmd),
        Command::Info {
            dataset,
            db,
            json,
            images,
            addr,
            map_id,
            token,
            tls_ca,
            tls_domain,
        } => match (dataset, db, addr) {
            (_, _, Some(addr)) => remote::print_map_info(
                &remote::ConnectArgs {
                    addr,
                    map_id,
                    token,
                    tls_ca,
                    tls_domain,
                },
                json,
            ),
            (_, Some(db), None) => info_cmd::info(&db, json, images),
            (Some(dataset), None, None) => synth_cmd::info(&dataset, json),
            (None, None, None) => unreachable!("clap requires --dataset, --db or --addr"),
        },
        Command::Demo {
            out,
            models,
            queries,
        } => {
            loading::models_dir(models.as_deref()).and_then(|m| synth_cmd::demo(&out, &m, queries))
        }
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
