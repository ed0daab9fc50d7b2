//! `pntr register --pairs FILE.csv [--method teaser|icp] [--noise-bound M]`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use nalgebra::Vector3;
use pntr_registration::icp::{icp_matched, IcpParams};
use pntr_registration::teaser::{solve, TeaserParams};
use pntr_registration::Rigid;
use serde_json::json;

/// Which solver.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum Method {
    /// Robust: maximum clique + GNC-TLS (survives most outliers).
    Teaser,
    /// Trimmed point-to-point ICP on the pairs, from identity (local; needs few outliers).
    Icp,
}

/// Arguments of `pntr register`.
#[derive(Args, Debug)]
pub struct RegisterArgs {
    /// CSV with header `sx,sy,sz,dx,dy,dz`, one correspondence per line.
    #[arg(long)]
    pub pairs: PathBuf,
    /// Solver.
    #[arg(long, value_enum, default_value_t = Method::Teaser)]
    pub method: Method,
    /// Bound on an inlier's residual, metres (teaser: noise bound; icp: final trimming radius).
    #[arg(long, default_value_t = 0.05)]
    pub noise_bound: f64,
}

/// A CSV problem: where and what.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("{path}:{line}: {message}")]
pub struct CsvError {
    /// The file.
    pub path: String,
    /// 1-based line number (1 is the header).
    pub line: usize,
    /// What is wrong.
    pub message: String,
}

/// Source and destination points, paired by index.
pub type Pairs = (Vec<Vector3<f64>>, Vec<Vector3<f64>>);

/// Parse `sx,sy,sz,dx,dy,dz` correspondences. Blank lines are skipped; everything else must be six
/// finite numbers. At least three rows are required.
pub fn parse_pairs(path: &str, text: &str) -> Result<Pairs, CsvError> {
    let err = |line: usize, message: String| CsvError {
        path: path.to_string(),
        line,
        message,
    };
    let mut lines = text.lines().enumerate();
    let header = loop {
        match lines.next() {
            Some((_, l)) if l.trim().is_empty() => continue,
            Some((i, l)) => break (i + 1, l),
            None => {
                return Err(err(
                    1,
                    "empty file; expected the header `sx,sy,sz,dx,dy,dz`".into(),
                ))
            }
        }
    };
    let cols: Vec<String> = header
        .1
        .trim_start_matches('\u{feff}')
        .split(',')
        .map(|c| c.trim().to_ascii_lowercase())
        .collect();
    if cols != ["sx", "sy", "sz", "dx", "dy", "dz"] {
        return Err(err(
            header.0,
            format!(
                "header is `{}`, expected `sx,sy,sz,dx,dy,dz`",
                header.1.trim()
            ),
        ));
    }
    const NAMES: [&str; 6] = ["sx", "sy", "sz", "dx", "dy", "dz"];
    let (mut src, mut dst) = (Vec::new(), Vec::new());
    for (i, l) in lines {
        if l.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = l.split(',').collect();
        if fields.len() != 6 {
            return Err(err(i + 1, format!("{} fields, expected 6", fields.len())));
        }
        let mut v = [0.0; 6];
        for (k, f) in fields.iter().enumerate() {
            let x: f64 = f.trim().parse().map_err(|_| {
                err(
                    i + 1,
                    format!("field `{}` is `{}`, not a number", NAMES[k], f.trim()),
                )
            })?;
            if !x.is_finite() {
                return Err(err(
                    i + 1,
                    format!("field `{}` is not finite ({x})", NAMES[k]),
                ));
            }
            v[k] = x;
        }
        src.push(Vector3::new(v[0], v[1], v[2]));
        dst.push(Vector3::new(v[3], v[4], v[5]));
    }
    if src.len() < 3 {
        return Err(err(
            header.0,
            format!("{} correspondences; at least 3 are needed", src.len()),
        ));
    }
    Ok((src, dst))
}

fn transform_json(t: &Rigid) -> (serde_json::Value, serde_json::Value) {
    let r = t.rotation.matrix();
    let rows: Vec<Vec<f64>> = (0..3)
        .map(|i| (0..3).map(|j| r[(i, j)]).collect())
        .collect();
    (
        json!(rows),
        json!([t.translation.x, t.translation.y, t.translation.z]),
    )
}

/// `pntr register`.
pub fn run(args: &RegisterArgs) -> Result<()> {
    if !(args.noise_bound.is_finite() && args.noise_bound > 0.0) {
        bail!("--noise-bound must be a positive number of metres");
    }
    let text = read(&args.pairs)?;
    let (src, dst) = parse_pairs(&args.pairs.display().to_string(), &text)?;
    let start = Instant::now();
    let out = match args.method {
        Method::Teaser => {
            let p = TeaserParams {
                noise_bound: args.noise_bound,
                ..TeaserParams::default()
            };
            let r = solve(&src, &dst, &p);
            let seconds = start.elapsed().as_secs_f64();
            let (rotation, translation) = transform_json(&r.transform);
            json!({
                "rotation": rotation, "translation": translation, "inliers": r.inliers, "valid": r.valid,
                "seconds": seconds, "method": "teaser", "clique_size": r.clique_size,
                "clique_exact": r.clique_exact, "reason": r.reason,
            })
        }
        Method::Icp => {
            let p = IcpParams {
                max_correspondence_m: f64::INFINITY,
                min_correspondence_m: args.noise_bound,
                ..IcpParams::default()
            };
            let r = icp_matched(&src, &dst, Rigid::identity(), &p);
            let seconds = start.elapsed().as_secs_f64();
            let (rotation, translation) = transform_json(&r.transform);
            json!({
                "rotation": rotation, "translation": translation, "inliers": r.inliers, "valid": r.valid,
                "seconds": seconds, "method": "icp", "rmse": r.rmse, "iterations": r.iterations,
                "converged": r.converged,
            })
        }
    };
    println!("{out}");
    Ok(())
}

fn read(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    String::from_utf8(bytes).with_context(|| format!("{}: not UTF-8 text", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_rejects() {
        let ok = "sx,sy,sz,dx,dy,dz\n0,0,0,1,1,1\n1,0,0,2,1,1\n\n0,1,0,1,2,1\n";
        let (s, d) = parse_pairs("f.csv", ok).unwrap();
        assert_eq!((s.len(), d[2]), (3, Vector3::new(1.0, 2.0, 1.0)));
        let cases = [
            ("", "empty file"),
            ("a,b,c\n", "expected `sx,sy,sz,dx,dy,dz`"),
            ("sx,sy,sz,dx,dy,dz\n0,0,0,1,1\n", "5 fields"),
            ("sx,sy,sz,dx,dy,dz\n0,0,x,1,1,1\n", "field `sz` is `x`"),
            (
                "sx,sy,sz,dx,dy,dz\n0,0,0,1,NaN,1\n",
                "field `dy` is not finite",
            ),
            ("sx,sy,sz,dx,dy,dz\n0,0,0,1,1,1\n", "at least 3"),
        ];
        for (text, want) in cases {
            let e = parse_pairs("f.csv", text).unwrap_err().to_string();
            assert!(e.contains(want) && e.starts_with("f.csv:"), "{e}");
        }
        let e =
            parse_pairs("f.csv", "sx,sy,sz,dx,dy,dz\n0,0,0,1,1,1\n1,1,1,1,1,inf\n").unwrap_err();
        assert_eq!(e.line, 3);
    }
}
