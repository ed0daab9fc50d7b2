//! Retrieval: which database images a query most likely shows.
//!
//! No pretrained place-recognition network can be obtained offline, so the default global descriptor is
//! VLAD over the local descriptors the feature stage already computes (XFeat 64-d by default), with a
//! codebook learned by faiss k-means on the map's own database images ([`vlad`]). A network exported
//! elsewhere plugs in through a small ONNX contract ([`onnx_global`]), and the paper's classical
//! baseline, a bag of ORB words with TF-IDF and an inverted file, is [`bow`]. Dense descriptors are
//! L2-normalised, so inner product is cosine similarity; the [`index`] is faiss (`auto` by default:
//! exact below 4096 images, PCA-whitening learned on the map above; HNSW or IVF by name), checked
//! against brute force in the tests; [`blas`] keeps query-time BLAS calls on the calling thread. [`global`] picks one of them by name and serialises it into the map.
//!
//! Naming: this is "VLAD over XFeat descriptors", not NetVLAD (no learned aggregation).

pub mod blas;
pub mod bow;
pub mod global;
pub mod index;
pub mod onnx_global;
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
    /// A global-descriptor model is missing or breaks its contract.
    #[error("{0}")]
    Model(String),
    /// Reading or writing a codebook failed.
    #[error("{path}: {message}")]
    File {
        /// The file.
        path: String,
        /// What went wrong.
        message: String,
    },
    /// A serialised part of a map is truncated or malformed.
    #[error("{0}")]
    Bytes(#[from] pntr_core::bytes::BytesError),
}

impl From<faiss::error::Error> for RetrievalError {
    fn from(e: faiss::error::Error) -> Self {
        RetrievalError::Faiss(e.to_string())
    }
}

/// Scale `v` to unit length (left as is when zero).
pub fn l2_normalise(v: &mut [f32]) {
    let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    if n > 0.0 {
        v.iter_mut().for_each(|x| *x /= n);
    }
}
