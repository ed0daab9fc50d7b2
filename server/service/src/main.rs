//! `pntr-server`: serve localization over gRPC. See the `pntr_service` crate docs and
//! `pntr-server --help`.

use std::io::Write;
use std::process::ExitCode;

use clap::Parser;
use pntr_service::config::{Args, Settings};

/// Resolves on the first SIGTERM or SIGINT.
async fn signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = ctrl_c => {}
                    _ = term.recv() => {}
                }
            }
            Err(_) => {
                let _ = ctrl_c.await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = ctrl_c.await;
    }
}

/// Listens for SIGHUP (reload the map files); never resolves where there is none.
struct Hangup {
    #[cfg(unix)]
    signal: Option<tokio::signal::unix::Signal>,
}

impl Hangup {
    fn new() -> Self {
        Self {
            #[cfg(unix)]
            signal: tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()).ok(),
        }
    }

    async fn recv(&mut self) {
        #[cfg(unix)]
        if let Some(s) = self.signal.as_mut() {
            s.recv().await;
            return;
        }
        std::future::pending::<()>().await
    }
}

fn main() -> ExitCode {
    let mut args = Args::parse();
    pntr_service::telemetry::init_tracing();
    // The embedded default: no map named anywhere -> the demo scene's map, generated and cached.
    if args.db.is_empty() && args.config.is_none() {
        let models = match pntr_features::models_dir::locate(args.models.as_deref()) {
            Ok(m) => m,
            Err(e) => {
                eprintln!("pntr-server: the demo map could not be made: {e}");
                return ExitCode::FAILURE;
            }
        };
        let cache = std::path::PathBuf::from(
            std::env::var_os("PNTR_DEMO_DIR").unwrap_or_else(|| "out/demo".into()),
        );
        match pntr_service::demo::ensure_demo_map(&cache, &models, &mut |m| {
            eprintln!("pntr-server: {m}")
        }) {
            Ok(p) => {
                eprintln!(
                    "pntr-server: no --db given; serving the demo map {}",
                    p.display()
                );
                args.db.push(p);
            }
            Err(e) => {
                eprintln!("pntr-server: no --db given and the demo map could not be made: {e}");
                return ExitCode::FAILURE;
            }
        }
    }
    let settings = match Settings::from_args(args) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("pntr-server: {e}");
            return ExitCode::from(2);
        }
    };
    tracing::info!(settings = ?settings, "starting");
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("pntr-io")
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("pntr-server: starting the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    runtime.block_on(async {
        let mut running = match pntr_service::start(settings).await {
            Ok(r) => r,
            Err(e) => {
                eprintln!("pntr-server: {e}");
                return ExitCode::FAILURE;
            }
        };
        // The one line on stdout, printed once the maps and models are loaded (so a wrapper that
        // waits for it never sees a server that then fails to load): scripts and tests read the
        // bound ports from it.
        tokio::select! {
            r = running.ready() => if let Err(e) = r {
                eprintln!("pntr-server: {e}");
                let _ = running.wait().await;
                return ExitCode::FAILURE;
            },
            _ = signal() => {
                tracing::info!("signal received while loading; shutting down");
                running.shutdown();
                return match running.wait().await {
                    Ok(()) => ExitCode::SUCCESS,
                    Err(e) => {
                        eprintln!("pntr-server: {e}");
                        ExitCode::FAILURE
                    }
                };
            }
        }
        let foxglove = running
            .foxglove_addr
            .map(|a| format!(" foxglove on ws://{a}"))
            .unwrap_or_default();
        println!(
            "pntr-server listening on {} metrics on {}{foxglove}",
            running.addr, running.metrics_addr
        );
        let _ = std::io::stdout().flush();
        let state = running.state.clone();
        let mut hangup = Hangup::new();
        let result = loop {
            tokio::select! {
                r = running.wait() => break r,
                _ = hangup.recv() => {
                    // Reloads run beside the serving (and one at a time, with admin calls).
                    tracing::info!("SIGHUP: reloading the map files that changed");
                    let state = state.clone();
                    tokio::spawn(async move {
                        match pntr_service::admin::reload(&state).await {
                            Ok(r) => tracing::info!(
                                reloaded = r.reloaded.len(),
                                unchanged = r.unchanged_map_ids.len(),
                                failed = r.failed.len(),
                                "SIGHUP reload done"
                            ),
                            Err(e) => tracing::warn!(error = %e, "SIGHUP reload refused"),
                        }
                    });
                }
                _ = signal() => {
                    tracing::info!("signal received; shutting down (a second signal exits at once)");
                    running.shutdown();
                    break tokio::select! {
                        r = running.wait() => r,
                        _ = signal() => {
                            eprintln!("pntr-server: second signal; exiting without draining");
                            return ExitCode::FAILURE;
                        }
                    };
                }
            }
        };
        match result {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("pntr-server: {e}");
                ExitCode::FAILURE
            }
        }
    })
}
