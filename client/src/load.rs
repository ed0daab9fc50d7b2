//! Load on a running server, as `pntr bench` sends it: single Localize calls, timed, and robots,
//! LocalizeStreams that send frames as a robot's camera does.
//!
//! Each robot opens one LocalizeStream and sends the frames in order, forward then back (a robot
//! driving the recorded path to and fro), one at a time: the next frame leaves when the previous
//! answer is in and, with a rate, not before its slot on the camera's clock. A slot that falls due
//! while the previous frame is unanswered is missed (a camera does not wait). Each frame carries the
//! robot's own monotonic stamp (`stamp_s`, seconds since the robot started), so turning back at the
//! end of the path is motion, not a recording started again. With churn, a robot leaves after a
//! number of answered frames (it closes its stream and waits for the server to end it) and comes
//! back at once on a new stream: the server builds and drops a stream's state again and again.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use pntr_service::proto::{self, localizer_client::LocalizerClient};
use pntr_service::tokio;
use pntr_service::tonic::transport::Channel;

use crate::remote::{authorized, request, stage_seconds, ConnectArgs};

/// One answered (or failed) request.
pub(crate) struct Record {
    /// Seconds from the send (or, open loop, the scheduled send) to the answer.
    pub latency: f64,
    /// The gRPC code's name when the call failed.
    pub code: Option<String>,
    /// Whether the answer was LOCALIZED.
    pub localized: bool,
    /// Server-reported seconds per stage.
    pub stages: Vec<(String, f64)>,
    /// `LocalizeResponse.map_version`.
    pub map_version: String,
}

impl Record {
    /// The record of an answer (or a failure) that took `latency` seconds.
    pub(crate) fn of(
        res: std::result::Result<proto::LocalizeResponse, pntr_service::tonic::Status>,
        latency: f64,
    ) -> Self {
        match res {
            Ok(r) => Record {
                latency,
                code: None,
                localized: r.status == proto::Status::Localized as i32,
                stages: stage_seconds(&r),
                map_version: r.map_version,
            },
            Err(s) => Record {
                latency,
                code: Some(pntr_service::service::code_name(s.code()).to_string()),
                localized: false,
                stages: Vec::new(),
                map_version: String::new(),
            },
        }
    }
}

/// One Localize call of `req`, timed from `started`.
pub(crate) async fn one(
    mut c: LocalizerClient<Channel>,
    connect: &ConnectArgs,
    req: proto::LocalizeRequest,
    started: Instant,
) -> Record {
    let res = match request(connect, req) {
        Ok(r) => c.localize(r).await.map(|r| r.into_inner()),
        Err(e) => Err(pntr_service::tonic::Status::internal(e.to_string())),
    };
    Record::of(res, started.elapsed().as_secs_f64())
}

/// The robots: how many, how fast, how long each stream lasts.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Robots {
    /// Concurrent LocalizeStreams.
    pub robots: usize,
    /// Frames per second each robot's camera delivers; `None`: back to back.
    pub rate_hz: Option<f64>,
    /// Answered frames after which a robot closes its stream and opens a new one; 0: never.
    pub churn_frames: usize,
}

/// What the robots did, counted as they go.
#[derive(Debug, Default)]
pub(crate) struct RobotTally {
    /// Camera slots that fell due while the robot's previous frame was unanswered.
    pub missed_slots: AtomicU64,
    /// Streams the server accepted (a robot's first and each one after churn or a failure; a
    /// refused one is an error, not a stream).
    pub streams_opened: AtomicU64,
}

/// Frame `i` of a path of `n` frames driven forward then back: 0, 1, ..., n-1, n-2, ..., 1, 0, 1, ...
pub(crate) fn to_and_fro(i: usize, n: usize) -> usize {
    if n <= 1 {
        return 0;
    }
    let period = 2 * (n - 1);
    let k = i % period;
    if k < n {
        k
    } else {
        period - k
    }
}

/// Drive `load.robots` robots until `end`: each answer (or failed call) goes to `sink`. Robots
/// start spread along the path (robot r at frame r * n / robots) so they do not send the same
/// frames at once. A stream the server ends with an error is recorded once with its code and
/// reopened after 100 ms.
pub(crate) async fn drive(
    c: LocalizerClient<Channel>,
    connect: ConnectArgs,
    frames: Arc<Vec<proto::LocalizeRequest>>,
    load: Robots,
    end: Instant,
    sink: Arc<dyn Fn(Record) + Send + Sync>,
    tally: Arc<RobotTally>,
) {
    let n = frames.len().max(1);
    let tasks: Vec<_> = (0..load.robots.max(1))
        .map(|r| {
            let (c, connect, frames, sink, tally) = (
                c.clone(),
                connect.clone(),
                frames.clone(),
                sink.clone(),
                tally.clone(),
            );
            let first = r * n / load.robots.max(1);
            tokio::spawn(async move {
                robot(c, &connect, &frames, load, first, end, &*sink, &tally).await;
            })
        })
        .collect();
    for t in tasks {
        let _ = t.await;
    }
}

/// One robot until `end`, starting at path step `first`.
#[allow(clippy::too_many_arguments)]
async fn robot(
    mut c: LocalizerClient<Channel>,
    connect: &ConnectArgs,
    frames: &[proto::LocalizeRequest],
    load: Robots,
    first: usize,
    end: Instant,
    sink: &(dyn Fn(Record) + Send + Sync),
    tally: &RobotTally,
) {
    let started = Instant::now();
    let period = load.rate_hz.map(|r| Duration::from_secs_f64(1.0 / r));
    let mut step = first;
    let mut slot: u64 = 0;
    'streams: while Instant::now() < end {
        let (tx, rx) = tokio::sync::mpsc::channel::<proto::LocalizeRequest>(1);
        let call = match authorized(
            connect,
            pntr_service::tokio_stream::wrappers::ReceiverStream::new(rx),
        ) {
            Ok(r) => c.localize_stream(r).await,
            Err(e) => Err(pntr_service::tonic::Status::internal(e.to_string())),
        };
        let mut answers = match call {
            Ok(a) => {
                tally.streams_opened.fetch_add(1, Ordering::Relaxed);
                a.into_inner()
            }
            Err(s) => {
                sink(Record::of(Err(s), 0.0));
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let mut sent_on_stream = 0usize;
        loop {
            if let Some(p) = period {
                // The next slot on the camera's clock; the ones already past were missed.
                let due = started + p * (slot as u32);
                let now = Instant::now();
                if due > now {
                    tokio::time::sleep_until(due.into()).await;
                } else {
                    let late = ((now - due).as_secs_f64() / p.as_secs_f64()) as u64;
                    tally.missed_slots.fetch_add(late, Ordering::Relaxed);
                    slot += late;
                }
                slot += 1;
            }
            if Instant::now() >= end {
                break 'streams;
            }
            let mut req = frames[to_and_fro(step, frames.len())].clone();
            req.map_id = connect.map_id.clone();
            req.stamp_s = Some(started.elapsed().as_secs_f64());
            step += 1;
            let sent = Instant::now();
            if tx.send(req).await.is_err() {
                break;
            }
            let res = match answers.message().await {
                Ok(Some(r)) => Ok(r),
                Ok(None) => Err(pntr_service::tonic::Status::unavailable(
                    "the server ended the stream",
                )),
                Err(s) => Err(s),
            };
            let failed = res.is_err();
            sink(Record::of(res, sent.elapsed().as_secs_f64()));
            if failed {
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue 'streams;
            }
            sent_on_stream += 1;
            if load.churn_frames > 0 && sent_on_stream >= load.churn_frames {
                break;
            }
        }
        // Leave: close the sending side and read the stream to its end, as a client that hangs up
        // cleanly does.
        drop(tx);
        while let Ok(Some(_)) = answers.message().await {}
    }
}

#[cfg(test)]
mod tests {
    use super::to_and_fro;

    #[test]
    fn a_path_is_driven_forward_then_back() {
        let seq: Vec<usize> = (0..9).map(|i| to_and_fro(i, 4)).collect();
        assert_eq!(seq, [0, 1, 2, 3, 2, 1, 0, 1, 2]);
        assert_eq!(to_and_fro(5, 1), 0);
        assert_eq!(to_and_fro(3, 2), 1);
    }
}
