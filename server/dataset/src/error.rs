use std::path::PathBuf;

/// Everything that can go wrong reading or writing the dataset. Every variant names the file; field
/// problems name the field too, so a user can find the bad record.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// A file-system operation failed.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The file is not a readable HDF5 file (missing, truncated, not HDF5).
    #[error("{path}: cannot open as HDF5: {message}")]
    Open {
        /// The file.
        path: PathBuf,
        /// What HDF5 said.
        message: String,
    },
    /// A field is missing, has the wrong dtype or shape, or holds an invalid value.
    #[error("{path}: field `{field}`: {problem}")]
    Field {
        /// The file.
        path: PathBuf,
        /// The HDF5 dataset name.
        field: String,
        /// What is wrong with it.
        problem: String,
    },
    /// The folder layout is not HPointLoc's.
    #[error("{path}: {problem}")]
    Layout {
        /// The folder or file.
        path: PathBuf,
        /// What is wrong.
        problem: String,
    },
}

impl DatasetError {
    pub(crate) fn field(path: &std::path::Path, field: &str, problem: impl Into<String>) -> Self {
        DatasetError::Field {
            path: path.to_path_buf(),
            field: field.to_string(),
            problem: problem.into(),
        }
    }
}
