//! The node's parameters from ROS 2's own command-line syntax (`--ros-args -p name:=value -r
//! from:=to -r __ns:=/NS -r __node:=NAME --params-file FILE.yaml`) and parameter-file format
//! (`<node or /** >: ros__parameters: {name: value}`); later arguments win over earlier ones, as in rcl.

use std::path::Path;

use anyhow::{bail, Context, Result};

/// Every parameter, with its defaults.
#[derive(Clone, Debug, PartialEq)]
pub struct Params {
    /// Colour topic: sensor_msgs/Image, or CompressedImage when the name ends in `/compressed`.
    pub rgb_topic: String,
    /// Depth topic, pixel-aligned with colour: sensor_msgs/Image (16UC1 mm or 32FC1 m), or
    /// CompressedImage when the name ends in `/compressedDepth`.
    pub depth_topic: String,
    /// The colour camera's sensor_msgs/CameraInfo.
    pub info_topic: String,
    /// The frame poses are published in.
    pub map_frame: String,
    /// The odometry frame (`map -> odom` is published).
    pub odom_frame: String,
    /// The robot's base frame (its pose is published).
    pub base_frame: String,
    /// Frames localized a second at most (the rest are dropped, the newest kept).
    pub rate_hz: f64,
    /// Topic of the pose (geometry_msgs/PoseWithCovarianceStamped); relative: under the namespace.
    pub pose_topic: String,
    /// The std_srvs/Trigger service that drops the track; relative: under the namespace.
    pub relocalize_service: String,
    /// How often the last `map -> odom` is broadcast again between answers, Hz.
    pub tf_publish_rate_hz: f64,
    /// Added to the stamp of `map -> odom` (AMCL's `transform_tolerance`), seconds.
    pub transform_tolerance_s: f64,
    /// Colour and depth messages whose stamps differ by at most this much are one frame, seconds.
    pub sync_slop_s: f64,
    /// Whether to publish `map -> odom` on /tf.
    pub publish_tf: bool,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            rgb_topic: "/camera/color/image_raw".into(),
            depth_topic: "/camera/aligned_depth_to_color/image_raw".into(),
            info_topic: "/camera/color/camera_info".into(),
            map_frame: "map".into(),
            odom_frame: "odom".into(),
            base_frame: "base_link".into(),
            rate_hz: 5.0,
            pose_topic: "pntr/pose".into(),
            relocalize_service: "pntr/relocalize".into(),
            tf_publish_rate_hz: 20.0,
            transform_tolerance_s: 0.1,
            sync_slop_s: 0.02,
            publish_tf: true,
        }
    }
}

/// A parameter value as written on the command line or in YAML.
#[derive(Clone, Debug, PartialEq)]
enum Value {
    Text(String),
    Number(f64),
    Bool(bool),
}

impl Value {
    fn from_cli(s: &str) -> Value {
        // rcl reads `-p` values as YAML scalars.
        match serde_yaml::from_str::<serde_yaml::Value>(s) {
            Ok(v) => Value::from_yaml(&v).unwrap_or_else(|| Value::Text(s.into())),
            Err(_) => Value::Text(s.into()),
        }
    }

    fn from_yaml(v: &serde_yaml::Value) -> Option<Value> {
        Some(match v {
            serde_yaml::Value::Bool(b) => Value::Bool(*b),
            serde_yaml::Value::Number(n) => Value::Number(n.as_f64()?),
            serde_yaml::Value::String(s) => Value::Text(s.clone()),
            _ => return None,
        })
    }
}

/// The node's name, namespace, remappings and parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct RosArgs {
    /// Node name (`__node`), default `pntr_ros`.
    pub node_name: String,
    /// Namespace (`__ns`), default `/`.
    pub namespace: String,
    /// Topic and service remappings, from -> to, as given.
    pub remaps: Vec<(String, String)>,
    /// The parameters.
    pub params: Params,
    /// `--log-level`: debug, info, warn or error.
    pub log_level: Option<String>,
}

impl RosArgs {
    /// Parse the arguments after `--ros-args` (up to a `--`).
    pub fn parse(args: &[String]) -> Result<RosArgs> {
        let mut node_name = "pntr_ros".to_string();
        let mut namespace = "/".to_string();
        let mut remaps = Vec::new();
        let mut set: Vec<(String, Value)> = Vec::new();
        let mut files = Vec::new();
        let mut log_level = None;
        let mut i = 0;
        while i < args.len() {
            let a = args[i].as_str();
            let next = |i: usize| {
                args.get(i + 1)
                    .cloned()
                    .with_context(|| format!("--ros-args: {a} needs a value"))
            };
            match a {
                "--" => break,
                "--ros-args" => {}
                "-p" | "--param" => {
                    let v = next(i)?;
                    let (name, value) = v.split_once(":=").with_context(|| {
                        format!("--ros-args: `{a} {v}`: a parameter is written name:=value")
                    })?;
                    set.push((name.trim().to_string(), Value::from_cli(value)));
                    i += 1;
                }
                "-r" | "--remap" => {
                    let v = next(i)?;
                    let (from, to) = v.split_once(":=").with_context(|| {
                        format!("--ros-args: `{a} {v}`: a remapping is written from:=to")
                    })?;
                    // `node_name:from:=to` applies to one node only.
                    let from = match from.split_once(':') {
                        Some((node, f)) if node == node_name || node == "pntr_ros" => f,
                        Some(_) => {
                            i += 2;
                            continue;
                        }
                        None => from,
                    };
                    match from {
                        "__ns" => namespace = to.to_string(),
                        "__node" | "__name" => node_name = to.to_string(),
                        _ => remaps.push((from.to_string(), to.to_string())),
                    }
                    i += 1;
                }
                "--params-file" => {
                    files.push((next(i)?, set.len()));
                    i += 1;
                }
                "--log-level" => {
                    let v = next(i)?;
                    // `--log-level debug`, or `--log-level NAME:=debug` for one logger.
                    let level = v.rsplit_once(":=").map_or(v.as_str(), |(_, l)| l).to_lowercase();
                    log_level = Some(match level.as_str() {
                        "debug" | "info" | "warn" | "error" => level,
                        "fatal" => "error".into(),
                        other => bail!("--ros-args: --log-level {other}: debug, info, warn, error or fatal"),
                    });
                    i += 1;
                }
                "--log-config-file" | "-e" | "--enclave" => i += 1,
                "--disable-rosout-logs"
                | "--enable-rosout-logs"
                | "--disable-stdout-logs"
                | "--enable-stdout-logs"
                | "--disable-external-lib-logs" => {}
                other => bail!(
                    "--ros-args: unknown argument {other:?} (supported: -p name:=value, -r from:=to, -r __ns:=/NS, -r __node:=NAME, --params-file FILE)"
                ),
            }
            i += 1;
        }
        if !namespace.starts_with('/') {
            namespace.insert(0, '/');
        }
        // Files first where they came first: an entry of the file is applied at its position.
        let mut all: Vec<(String, Value, bool)> = Vec::new();
        let mut from = 0;
        let cli = |v: &[(String, Value)]| {
            v.iter()
                .map(|(n, x)| (n.clone(), x.clone(), false))
                .collect::<Vec<_>>()
        };
        for (file, at) in &files {
            all.extend(cli(&set[from..*at]));
            all.extend(
                read_params_file(Path::new(file), &node_name, &namespace)?
                    .into_iter()
                    .map(|(n, v)| (n, v, true)),
            );
            from = *at;
        }
        all.extend(cli(&set[from..]));
        let mut params = Params::default();
        for (name, value, from_file) in all {
            match apply(&mut params, &name, value) {
                // A shared parameter file holds other nodes' keys (`qos_overrides...`, a filter's
                // settings): skipped, as rclcpp skips parameters a node does not declare.
                Err(e) if from_file && e.to_string().starts_with("unknown parameter") => {
                    if !name.starts_with("qos_overrides.") {
                        eprintln!(
                            "warning: --params-file: {name} is not a pntr-ros parameter: ignored"
                        );
                    }
                }
                other => other?,
            }
        }
        check_ranges(&params)?;
        Ok(RosArgs {
            node_name,
            namespace,
            remaps,
            params,
            log_level,
        })
    }

    /// A topic or service name after remapping, resolved against the namespace (absolute
    /// names stay, relative ones are put under the namespace, `~/x` under the node).
    pub fn resolve(&self, name: &str) -> String {
        let ns = self.namespace.trim_end_matches('/');
        let full = |n: &str| -> String {
            if n.starts_with('/') {
                n.to_string()
            } else if let Some(rest) = n.strip_prefix("~/") {
                format!("{ns}/{}/{rest}", self.node_name)
            } else {
                format!("{ns}/{n}")
            }
        };
        let resolved = full(name);
        for (from, to) in &self.remaps {
            if full(from) == resolved {
                return full(to);
            }
        }
        resolved
    }
}

/// Values outside what each parameter means are refused at start, naming the parameter.
fn check_ranges(p: &Params) -> Result<()> {
    let within = |name: &str, v: f64, lo: f64, hi: f64, what: &str| -> Result<()> {
        if v.is_finite() && (lo..=hi).contains(&v) {
            Ok(())
        } else {
            bail!("parameter {name}: {v} ({what})")
        }
    };
    within(
        "rate_hz",
        p.rate_hz,
        0.01,
        1000.0,
        "frames a second, 0.01 to 1000",
    )?;
    if p.tf_publish_rate_hz != 0.0 {
        within(
            "tf_publish_rate_hz",
            p.tf_publish_rate_hz,
            0.1,
            1000.0,
            "Hz, 0 (off) or 0.1 to 1000",
        )?;
    }
    within(
        "transform_tolerance_s",
        p.transform_tolerance_s,
        0.0,
        10.0,
        "seconds, 0 to 10",
    )?;
    within(
        "sync_slop_s",
        p.sync_slop_s,
        0.0,
        1.0,
        "seconds, 0 to 1: colour and depth of one frame",
    )?;
    for (name, v) in [
        ("rgb_topic", &p.rgb_topic),
        ("depth_topic", &p.depth_topic),
        ("info_topic", &p.info_topic),
        ("pose_topic", &p.pose_topic),
        ("relocalize_service", &p.relocalize_service),
        ("map_frame", &p.map_frame),
        ("odom_frame", &p.odom_frame),
        ("base_frame", &p.base_frame),
    ] {
        if v.trim().is_empty() {
            bail!("parameter {name} is empty");
        }
    }
    Ok(())
}

fn apply(p: &mut Params, name: &str, value: Value) -> Result<()> {
    let text = |v: &Value| match v {
        Value::Text(s) => Ok(s.clone()),
        other => bail!("parameter {name}: a string expected, got {other:?}"),
    };
    let number = |v: &Value| match v {
        Value::Number(x) => Ok(*x),
        other => bail!("parameter {name}: a number expected, got {other:?}"),
    };
    match name {
        "rgb_topic" => p.rgb_topic = text(&value)?,
        "depth_topic" => p.depth_topic = text(&value)?,
        "info_topic" => p.info_topic = text(&value)?,
        "map_frame" => p.map_frame = text(&value)?,
        "odom_frame" => p.odom_frame = text(&value)?,
        "base_frame" => p.base_frame = text(&value)?,
        "pose_topic" => p.pose_topic = text(&value)?,
        "relocalize_service" => p.relocalize_service = text(&value)?,
        "rate_hz" => p.rate_hz = number(&value)?,
        "tf_publish_rate_hz" => p.tf_publish_rate_hz = number(&value)?,
        "transform_tolerance_s" => p.transform_tolerance_s = number(&value)?,
        "sync_slop_s" => p.sync_slop_s = number(&value)?,
        "publish_tf" => match value {
            Value::Bool(b) => p.publish_tf = b,
            other => bail!("parameter {name}: true or false expected, got {other:?}"),
        },
        "use_sim_time" => {}
        other => bail!(
            "unknown parameter {other:?} (known: rgb_topic, depth_topic, info_topic, map_frame, odom_frame, base_frame, rate_hz, pose_topic, relocalize_service, tf_publish_rate_hz, transform_tolerance_s, sync_slop_s, publish_tf)"
        ),
    }
    Ok(())
}

/// The entries of a ROS 2 parameter file that apply to this node: under `/**`, `**`, the node's
/// name or its fully qualified name (with or without the leading slash), each with `ros__parameters`.
fn read_params_file(path: &Path, node: &str, namespace: &str) -> Result<Vec<(String, Value)>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("--params-file {}: cannot read it", path.display()))?;
    let doc: serde_yaml::Value = serde_yaml::from_str(&text)
        .with_context(|| format!("--params-file {}: not YAML", path.display()))?;
    let map = doc.as_mapping().with_context(|| {
        format!(
            "--params-file {}: a mapping of node names expected",
            path.display()
        )
    })?;
    let fqn = format!("{}/{node}", namespace.trim_end_matches('/'));
    let mut out = Vec::new();
    for (key, body) in map {
        let key = key.as_str().unwrap_or_default();
        if !(key == node || node_key_matches(key, &fqn)) {
            continue;
        }
        let Some(params) = body.get("ros__parameters") else {
            bail!(
                "--params-file {}: {key:?} has no `ros__parameters` (the file format is `{node}: ros__parameters: {{name: value}}`)",
                path.display()
            );
        };
        let flat = flatten(params, "");
        for (name, v) in flat {
            let value = Value::from_yaml(&v).with_context(|| {
                format!(
                    "--params-file {}: parameter {name}: a scalar expected",
                    path.display()
                )
            })?;
            out.push((name, value));
        }
    }
    Ok(out)
}

/// Whether a parameter file's node key applies to the node `fqn` (`/ns/name`): rcl's wildcards,
/// `*` one name token and `**` any number of them (`/**`, `/**/pntr_ros`, `/robot*/pntr_ros`); a
/// key without the leading slash is taken as absolute.
fn node_key_matches(key: &str, fqn: &str) -> bool {
    fn token(pattern: &str, name: &str) -> bool {
        match pattern.split_once('*') {
            None => pattern == name,
            Some((head, tail)) => {
                name.starts_with(head) && (head.len()..=name.len()).any(|i| token(tail, &name[i..]))
            }
        }
    }
    fn tokens(p: &[&str], n: &[&str]) -> bool {
        match (p.first(), n.first()) {
            (None, None) => true,
            (Some(&"**"), _) => (0..=n.len()).any(|i| tokens(&p[1..], &n[i..])),
            (Some(t), Some(m)) => token(t, m) && tokens(&p[1..], &n[1..]),
            _ => false,
        }
    }
    let split = |s: &str| -> Vec<String> {
        s.trim_start_matches('/')
            .split('/')
            .filter(|t| !t.is_empty())
            .map(String::from)
            .collect()
    };
    let (p, n) = (split(key), split(fqn));
    let p: Vec<&str> = p.iter().map(String::as_str).collect();
    let n: Vec<&str> = n.iter().map(String::as_str).collect();
    tokens(&p, &n)
}

/// Nested parameter maps as dotted names (`a: {b: 1}` is `a.b`).
fn flatten(v: &serde_yaml::Value, prefix: &str) -> Vec<(String, serde_yaml::Value)> {
    match v.as_mapping() {
        Some(m) => m
            .iter()
            .flat_map(|(k, v)| {
                let k = k.as_str().unwrap_or_default();
                let name = if prefix.is_empty() {
                    k.to_string()
                } else {
                    format!("{prefix}.{k}")
                };
                flatten(v, &name)
            })
            .collect(),
        None => vec![(prefix.to_string(), v.clone())],
    }
}

/// Group the command line into (pntr-ros arguments, arguments after `--ros-args`).
pub fn split_args(all: Vec<String>) -> (Vec<String>, Vec<String>) {
    match all.iter().position(|a| a == "--ros-args") {
        Some(i) => {
            let mut own = all[..i].to_vec();
            let rest = &all[i + 1..];
            let end = rest.iter().position(|a| a == "--").unwrap_or(rest.len());
            own.extend(rest.get(end + 1..).unwrap_or_default().iter().cloned());
            (own, rest[..end].to_vec())
        }
        None => (all, Vec::new()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn command_line_file_and_namespace() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("p.yaml");
        std::fs::write(
            &file,
            "/**:\n  ros__parameters:\n    rate_hz: 2\n    base_frame: base_footprint\nother_node:\n  ros__parameters:\n    rate_hz: 9.0\n",
        )
        .unwrap();
        let a = RosArgs::parse(&args(&format!(
            "-p rate_hz:=3.5 --params-file {} -r __ns:=/robot1 -p map_frame:=world -r pntr/pose:=fix",
            file.display()
        )))
        .unwrap();
        // The file comes after `-p rate_hz:=3.5`, so it wins; its other_node entry does not apply.
        assert_eq!(a.params.rate_hz, 2.0);
        assert_eq!(a.params.base_frame, "base_footprint");
        assert_eq!(a.params.map_frame, "world");
        assert_eq!(a.namespace, "/robot1");
        assert_eq!(a.resolve(&a.params.pose_topic), "/robot1/fix");
        assert_eq!(
            a.resolve(&a.params.relocalize_service),
            "/robot1/pntr/relocalize"
        );
        assert_eq!(a.resolve(&a.params.rgb_topic), "/camera/color/image_raw");
        let e = RosArgs::parse(&args("-p rate_hz:=fast"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("rate_hz") && e.contains("number"), "{e}");
        let e = RosArgs::parse(&args("-p rgb_topik:=/x"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("unknown parameter"), "{e}");
        for (key, applies) in [
            ("/**", true),
            ("/**/pntr_ros", true),
            ("/robot*/pntr_ros", true),
            ("robot1/pntr_ros", true),
            ("/robot1/*", true),
            ("/robot2/pntr_ros", false),
            ("/pntr_ros", false),
        ] {
            assert_eq!(node_key_matches(key, "/robot1/pntr_ros"), applies, "{key}");
        }
        // A shared file's keys of other nodes are skipped; a typo on the command line is not.
        std::fs::write(
            &file,
            "/**:\n  ros__parameters:\n    qos_overrides./tf.publisher.depth: 10\n    use_tf_static: true\n    rate_hz: 3.0\n",
        )
        .unwrap();
        let a = RosArgs::parse(&args(&format!("--params-file {}", file.display()))).unwrap();
        assert_eq!(a.params.rate_hz, 3.0);
        for bad in [
            "-p sync_slop_s:=-1",
            "-p tf_publish_rate_hz:=1e-30",
            "-p rate_hz:=0",
            "-p base_frame:=''",
        ] {
            assert!(RosArgs::parse(&args(bad)).is_err(), "{bad}");
        }
        let (own, ros) = split_args(args("pntr-ros --addr h:1 --ros-args -p a:=1 -- --map-id m"));
        assert_eq!(own, args("pntr-ros --addr h:1 --map-id m"));
        assert_eq!(ros, args("-p a:=1"));
    }
}
