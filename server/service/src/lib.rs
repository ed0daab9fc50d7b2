//! `pntr-server`: the gRPC localization service (`pntr.v1.Localizer`, `proto/pntr/v1/localizer.proto`).
//!
//! A robot sends RGB-D frames (one call each, or a stream); the server answers with the camera's pose
//! in a prebuilt map. Load tests push it for frames per second and Prometheus scrapes it.
//!
//! Why it is built this way:
//! - **Whole map in memory, loaded once.** Maps (`pntr build-db`) and models load at start, in the
//!   background: the ports are bound first and `grpc.health.v1` says NOT_SERVING until everything is
//!   loaded, then SERVING ([`server`]).
//! - **CPU work off the async runtime, bounded.** tonic's runtime only waits; frames are decoded on
//!   blocking threads, at most max(2, workers) at once (so a huge PNG never stalls health checks, and
//!   decoded frames waiting for the queue take bounded memory); a fixed pool of worker threads, each with its own model sessions, runs the pipeline, fed by a
//!   bounded queue. A full queue is RESOURCE_EXHAUSTED at once, not unbounded latency, and client
//!   deadlines are honoured: work whose deadline passed while queued is dropped, DEADLINE_EXCEEDED
//!   ([`engine`], [`service`]).
//! - **Bad input is a status, never a panic.** Every frame is checked before it takes a queue slot,
//!   against size limits before anything is allocated; each refusal says what to fix ([`decode`]).
//!   Missing depth (0, NaN, inf, negative) is skipped as cameras send it, not refused.
//! - **No system protoc.** `build.rs` compiles the proto with protox (pure Rust) and feeds the
//!   descriptor set to tonic's generator; the same descriptors serve reflection.
//! - **Operable.** Settings from flags, `PNTR_*` variables and a TOML/JSON file, validated at start
//!   ([`config`]); Prometheus metrics on their own port and tracing spans carrying the request id
//!   ([`telemetry`]); graceful drain on SIGTERM/SIGINT; optional TLS (rustls) and bearer token.
//! - **Watching costs the robots nothing.** The live Foxglove view (`--foxglove`) draws frames on a
//!   thread of its own behind a queue of two, and each viewer's backlog is bounded: a slow viewer
//!   loses frames, never the robots' latency or the server's memory ([`visual::Live`]; its front
//!   door also serves clients asking for the protocol's earlier name, [`live_proxy`]).
//! - **One wire definition for clients too.** [`wire`] builds requests from pntr's image types, so the
//!   tests and `pntr eval --remote` encode frames exactly as the server decodes them. Clients use the
//!   re-exported [`tonic`] (and health / reflection clients) so their versions always match.

pub mod admin;
pub mod config;
pub mod decode;
pub mod demo;
pub mod engine;
pub mod live_proxy;
pub mod ros_bag;
pub mod server;
pub mod service;
pub mod telemetry;
pub mod track;
pub mod visual;
pub mod wire;

pub use server::{start, LoadState, Running, ServerError, ADMIN_SERVICE_NAME, SERVICE_NAME};

pub use {tokio, tokio_stream, tonic, tonic_health, tonic_reflection};

/// Types and client/server stubs generated from `proto/pntr/v1/localizer.proto`.
#[allow(missing_docs, clippy::all, clippy::pedantic)]
pub mod proto {
    tonic::include_proto!("pntr.v1");

    /// The encoded `FileDescriptorSet` of the API (served by reflection).
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        include_bytes!(concat!(env!("OUT_DIR"), "/pntr_v1_descriptor.bin"));
}
