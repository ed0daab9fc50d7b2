//! Finding scenes and Points in a dataset folder.

use std::path::{Path, PathBuf};

use crate::{DatasetError, PointReader};

/// The folder under the dataset root that holds the scenes.
pub const DATASET_DIR: &str = "HPointLoc_dataset";

/// The file of Point `index` of `scene` under `root` (the folder that contains `HPointLoc_dataset`).
pub fn point_path(root: &Path, scene: &str, index: u32) -> PathBuf {
    root.join(DATASET_DIR)
        .join(scene)
        .join(format!("{scene}_point{index}.hdf5"))
}

/// The Point index encoded in a file name: the second-to-last run of digits, as the HPointLoc code
/// reads it (`1LXtFkjw3qL_point12.hdf5` -> 12; the last run is the `5` of `hdf5`).
pub fn point_index_from_name(file_name: &str) -> Option<u32> {
    let mut runs = Vec::new();
    let mut cur = String::new();
    for c in file_name.chars() {
        if c.is_ascii_digit() {
            cur.push(c);
        } else if !cur.is_empty() {
            runs.push(std::mem::take(&mut cur));
        }
    }
    if !cur.is_empty() {
        runs.push(cur);
    }
    if runs.len() < 2 {
        return None;
    }
    runs[runs.len() - 2].parse().ok()
}

/// One Point file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PointEntry {
    /// The scene it belongs to.
    pub scene: String,
    /// The Point index from the file name.
    pub index: u32,
    /// The file.
    pub path: PathBuf,
}

impl PointEntry {
    /// Open the file and validate its fields.
    pub fn open(&self) -> Result<PointReader, DatasetError> {
        PointReader::open(&self.path)
    }

    /// A stable id for a database view of this Point: `<scene>/point<N>/db<i>`.
    pub fn db_image_id(&self, view: usize) -> String {
        format!("{}/point{}/db{}", self.scene, self.index, view)
    }

    /// A stable id for a query of this Point: `<scene>/point<N>/q<i>`.
    pub fn query_id(&self, query: usize) -> String {
        format!("{}/point{}/q{}", self.scene, self.index, query)
    }
}

/// One scene: a folder of Point files sharing a world frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SceneEntry {
    /// The scene name (folder name).
    pub name: String,
    /// Its folder.
    pub dir: PathBuf,
    /// Its Points, sorted by index.
    pub points: Vec<PointEntry>,
}

/// The scenes of a dataset folder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DatasetIndex {
    /// The folder holding the scene folders (`<root>/HPointLoc_dataset`).
    pub dir: PathBuf,
    /// Scenes sorted by name.
    pub scenes: Vec<SceneEntry>,
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

impl DatasetIndex {
    /// List a dataset. `root` may be the folder containing `HPointLoc_dataset` or that folder itself.
    pub fn open(root: &Path) -> Result<Self, DatasetError> {
        let dir = if root.join(DATASET_DIR).is_dir() {
            root.join(DATASET_DIR)
        } else if root.file_name().is_some_and(|n| n == DATASET_DIR) && root.is_dir() {
            root.to_path_buf()
        } else {
            return Err(DatasetError::Layout {
                path: root.to_path_buf(),
                problem: format!("no `{DATASET_DIR}` folder here (expected <root>/{DATASET_DIR}/<scene>/<scene>_point<N>.hdf5)"),
            });
        };
        let mut scenes = Vec::new();
        let mut entries: Vec<_> = std::fs::read_dir(&dir)
            .map_err(io_err(&dir))?
            .collect::<Result<_, _>>()
            .map_err(io_err(&dir))?;
        entries.sort_by_key(|e| e.file_name());
        for e in entries {
            let sdir = e.path();
            if !sdir.is_dir() {
                continue;
            }
            let name = e.file_name().to_string_lossy().into_owned();
            let scene = Self::list_scene(&name, &sdir)?;
            if !scene.points.is_empty() {
                scenes.push(scene);
            }
        }
        if scenes.is_empty() {
            return Err(DatasetError::Layout {
                path: dir,
                problem: "no scene folder with Point files (<scene>_point<N>.hdf5)".into(),
            });
        }
        Ok(Self { dir, scenes })
    }

    fn list_scene(name: &str, sdir: &Path) -> Result<SceneEntry, DatasetError> {
        let mut points = Vec::new();
        for f in std::fs::read_dir(sdir).map_err(io_err(sdir))? {
            let f = f.map_err(io_err(sdir))?;
            let fname = f.file_name().to_string_lossy().into_owned();
            if !fname.ends_with(".hdf5") || !fname.contains("_point") {
                continue;
            }
            let index = point_index_from_name(&fname).ok_or_else(|| DatasetError::Layout {
                path: f.path(),
                problem: "file name carries no Point index".into(),
            })?;
            points.push(PointEntry {
                scene: name.to_string(),
                index,
                path: f.path(),
            });
        }
        points.sort_by_key(|p| p.index);
        if let Some(w) = points.windows(2).find(|w| w[0].index == w[1].index) {
            return Err(DatasetError::Layout {
                path: w[1].path.clone(),
                problem: format!("Point index {} appears twice in scene {name}", w[0].index),
            });
        }
        Ok(SceneEntry {
            name: name.to_string(),
            dir: sdir.to_path_buf(),
            points,
        })
    }

    /// The scene called `name`.
    pub fn scene(&self, name: &str) -> Result<&SceneEntry, DatasetError> {
        self.scenes
            .iter()
            .find(|s| s.name == name)
            .ok_or_else(|| DatasetError::Layout {
                path: self.dir.clone(),
                problem: format!(
                    "no scene `{name}`; scenes here: {}",
                    self.scenes
                        .iter()
                        .map(|s| s.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_index_is_second_to_last_integer() {
        assert_eq!(point_index_from_name("1LXtFkjw3qL_point0.hdf5"), Some(0));
        assert_eq!(point_index_from_name("1LXtFkjw3qL_point17.hdf5"), Some(17));
        assert_eq!(point_index_from_name("synth003_point4.hdf5"), Some(4));
        assert_eq!(point_index_from_name("scene.hdf5"), None);
        let p = point_path(Path::new("/d"), "s", 3);
        assert_eq!(p, PathBuf::from("/d/HPointLoc_dataset/s/s_point3.hdf5"));
    }
}
