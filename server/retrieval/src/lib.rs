//! Retrieval: which database images a query most likely shows.
//!
//! No pretrained place-recognition network can be obtained offline, so the default global descriptor is
//! VLAD over the local descriptors the feature stage already computes (XFeat 64-d by default), with a
//! codebook learned by faiss k-means on the map's own database images ([`vlad`]). Descriptors are
//! L2-normalised, so inner product is cosine similarity; the [`index`] is faiss (exact flat by default,
//! HNSW for very large maps), checked against brute force in the tests.
//!
//! Naming: this is "VLAD over XFeat descriptors", not NetVLAD (no learned aggregation).

pub mod index;
pub mod vlad;

/// Errors of retrieval.
#[derive(Debug, thiserror::Error)]
pub enum RetrievalError {
    /// Inputs that cannot be used (empty, wrong dimensions).
    #[error("invalid input: {0}")]
    Input(String),
    /// faiss reported an error.
    #[error("faiss: {0}")]
    Faiss(String),
    /// Reading or writing a codebook failed.
    #[error("{path}: {message}")]
    File {
        /// The file.
        path: String,
        /// What went wrong.
        message: String,
    },
}

impl From<faiss::error::Error> for RetrievalError {
    fn from(e: faiss::error::Error) -> Self {
        RetrievalError::Faiss(e.to_string())
    }
}
