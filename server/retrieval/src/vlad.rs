//! VLAD (Jegou et al. 2010; Arandjelovic and Zisserman 2013 for intra-normalisation): sum the residuals
//! of local descriptors to their nearest codeword, per codeword; normalise each codeword's block
//! (intra-normalisation, which damps bursty repeated structures such as tiles), apply signed square
//! root (power normalisation), then L2-normalise the whole vector.

use std::io::Write;
use std::path::Path;

use crate::RetrievalError;

/// A VLAD codebook: `k` centroids of `dim`-long local descriptors.
#[derive(Debug, Clone, PartialEq)]
pub struct Codebook {
    /// Local descriptor length.
    pub dim: usize,
    /// Number of codewords.
    pub k: usize,
    /// `k * dim` centroid values, row-major.
    pub centroids: Vec<f32>,
}

const MAGIC: &[u8; 8] = b"PNTRVLAD";
const VERSION: u32 = 1;

use pntr_core::bytes::fnv1a;

impl Codebook {
    /// Learn `k` codewords from `descriptors` (`n * dim` values) by faiss k-means (25 iterations,
    /// fixed `seed`, so the same input gives the same codebook).
    pub fn train(
        descriptors: &[f32],
        dim: usize,
        k: usize,
        seed: u32,
    ) -> Result<Self, RetrievalError> {
        if dim == 0 || k == 0 || descriptors.len() % dim != 0 {
            return Err(RetrievalError::Input(format!(
                "{} values are not a whole number of {dim}-d descriptors, or k = {k}",
                descriptors.len()
            )));
        }
        let n = descriptors.len() / dim;
        if n < k {
            return Err(RetrievalError::Input(format!(
                "{n} descriptors cannot train {k} codewords"
            )));
        }
        let mut params = faiss::cluster::ClusteringParameters::new();
        params.set_niter(25);
        params.set_seed(seed);
        params.set_max_points_per_centroid(1024);
        let mut clustering =
            faiss::cluster::Clustering::new_with_params(dim as u32, k as u32, &params)?;
        let mut quantizer = faiss::index::flat::FlatIndexImpl::new_l2(dim as u32)?;
        clustering.train(descriptors, &mut quantizer)?;
        let centroids: Vec<f32> = clustering
            .centroids()?
            .into_iter()
            .flatten()
            .copied()
            .collect();
        Ok(Self { dim, k, centroids })
    }

    /// Length of the VLAD vector.
    pub fn vlad_dim(&self) -> usize {
        self.k * self.dim
    }

    /// The nearest codeword of every descriptor (`n * dim` values, whole rows): the largest
    /// `d . c - |c|^2 / 2` (the smallest `|d - c|^2` less the constant `|d|^2 / 2`), the first among
    /// equals, with every dot product from one matrix product (matrixmultiply's sgemm).
    fn nearest_all(&self, descriptors: &[f32]) -> Vec<usize> {
        let n = descriptors.len() / self.dim;
        let (Ok(d), Ok(c)) = (
            ndarray::ArrayView2::from_shape((n, self.dim), descriptors),
            ndarray::ArrayView2::from_shape((self.k, self.dim), &self.centroids[..]),
        ) else {
            return Vec::new();
        };
        let dots = d.dot(&c.t());
        let half_norms: Vec<f32> = self
            .centroids
            .chunks_exact(self.dim)
            .map(|c| c.iter().map(|x| x * x).sum::<f32>() / 2.0)
            .collect();
        dots.rows()
            .into_iter()
            .map(|row| {
                let mut best = (0, f32::NEG_INFINITY);
                for (j, (&dot, &h)) in row.iter().zip(&half_norms).enumerate() {
                    let score = dot - h;
                    if score > best.1 {
                        best = (j, score);
                    }
                }
                best.0
            })
            .collect()
    }

    /// The VLAD vector of one image's local descriptors (`n * dim` values). An image without
    /// descriptors gets the zero vector (it matches nothing).
    pub fn vlad(&self, descriptors: &[f32]) -> Result<Vec<f32>, RetrievalError> {
        if descriptors.len() % self.dim != 0 {
            return Err(RetrievalError::Input(format!(
                "{} values are not a whole number of {}-d descriptors",
                descriptors.len(),
                self.dim
            )));
        }
        let mut v = vec![0f32; self.vlad_dim()];
        let nearest = self.nearest_all(descriptors);
        for (d, &c) in descriptors.chunks_exact(self.dim).zip(&nearest) {
            let cw = &self.centroids[c * self.dim..(c + 1) * self.dim];
            for ((acc, x), m) in v[c * self.dim..(c + 1) * self.dim]
                .iter_mut()
                .zip(d)
                .zip(cw)
            {
                *acc += x - m;
            }
        }
        for block in v.chunks_exact_mut(self.dim) {
            let n = block.iter().map(|x| x * x).sum::<f32>().sqrt();
            if n > 0.0 {
                block.iter_mut().for_each(|x| *x /= n);
            }
        }
        for x in &mut v {
            *x = x.signum() * x.abs().sqrt();
        }
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        if n > 0.0 {
            v.iter_mut().for_each(|x| *x /= n);
        }
        Ok(v)
    }

    /// The file contents [`Codebook::save`] writes: magic, version, dim, k, the centroids as
    /// little-endian f32, and an FNV-1a checksum of all that.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut bytes = Vec::with_capacity(32 + self.centroids.len() * 4);
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&VERSION.to_le_bytes());
        bytes.extend_from_slice(&(self.dim as u32).to_le_bytes());
        bytes.extend_from_slice(&(self.k as u32).to_le_bytes());
        for c in &self.centroids {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
        let sum = fnv1a(&bytes);
        bytes.extend_from_slice(&sum.to_le_bytes());
        bytes
    }

    /// Parse [`Codebook::to_bytes`] output, checking magic, version, size and checksum.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        if bytes.len() < 28 || &bytes[..8] != MAGIC {
            return Err("not a pntr VLAD codebook".into());
        }
        let u32_at = |i: usize| u32::from_le_bytes(bytes[i..i + 4].try_into().expect("4 bytes"));
        if u32_at(8) != VERSION {
            return Err(format!(
                "codebook version {} (this build reads {VERSION})",
                u32_at(8)
            ));
        }
        let (dim, k) = (u32_at(12) as usize, u32_at(16) as usize);
        let body = dim
            .checked_mul(k)
            .and_then(|x| x.checked_mul(4))
            .and_then(|x| x.checked_add(20));
        match body {
            Some(body) if dim > 0 && k > 0 && bytes.len() == body + 8 => {
                let stored = u64::from_le_bytes(bytes[body..].try_into().expect("8 bytes"));
                if stored != fnv1a(&bytes[..body]) {
                    return Err("checksum mismatch (corrupted file)".into());
                }
                let centroids = bytes[20..body]
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                    .collect();
                Ok(Self { dim, k, centroids })
            }
            _ => Err(format!(
                "{} bytes do not hold {k} x {dim} centroids",
                bytes.len()
            )),
        }
    }

    /// Write to `path` via a temporary file renamed into place.
    pub fn save(&self, path: &Path) -> Result<(), RetrievalError> {
        let err = |message: String| RetrievalError::File {
            path: path.display().to_string(),
            message,
        };
        let bytes = self.to_bytes();
        let tmp = path.with_extension(format!("partial-{}", std::process::id()));
        let mut f = std::fs::File::create(&tmp).map_err(|e| err(e.to_string()))?;
        f.write_all(&bytes)
            .and_then(|_| f.sync_all())
            .map_err(|e| err(e.to_string()))?;
        std::fs::rename(&tmp, path).map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            err(e.to_string())
        })
    }

    /// Read a codebook written by [`Codebook::save`].
    pub fn load(path: &Path) -> Result<Self, RetrievalError> {
        let err = |message: String| RetrievalError::File {
            path: path.display().to_string(),
            message,
        };
        let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
        Self::from_bytes(&bytes).map_err(err)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` rows of `dim` values in -0.5..0.5 from a seeded xorshift.
    fn rows(n: usize, dim: usize, seed: u64) -> Vec<f32> {
        let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..n * dim)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 40) as f32 / (1u64 << 24) as f32 - 0.5
            })
            .collect()
    }

    #[test]
    fn every_descriptor_goes_to_its_nearest_codeword() {
        let (dim, k) = (64, 32);
        let book = Codebook {
            dim,
            k,
            centroids: rows(k, dim, 1),
        };
        let d = rows(500, dim, 2);
        let got = book.nearest_all(&d);
        assert_eq!(got.len(), 500);
        for (i, row) in d.chunks_exact(dim).enumerate() {
            let dist = |c: usize| -> f64 {
                book.centroids[c * dim..(c + 1) * dim]
                    .iter()
                    .zip(row)
                    .map(|(a, b)| ((a - b) as f64).powi(2))
                    .sum()
            };
            let want = (0..k).min_by(|&a, &b| dist(a).total_cmp(&dist(b))).unwrap();
            assert!(
                got[i] == want || (dist(got[i]) - dist(want)).abs() < 1e-5,
                "descriptor {i}: codeword {} at {} instead of {want} at {}",
                got[i],
                dist(got[i]),
                dist(want)
            );
        }
        // Descriptors equal to codewords go to those codewords; the first of two equal ones wins.
        let mut twin = book.clone();
        twin.centroids[5 * dim..6 * dim].copy_from_slice(&book.centroids[..dim]);
        assert_eq!(twin.nearest_all(&book.centroids[..3 * dim]), vec![0, 1, 2]);
        // The VLAD vector is unit length, and zero without descriptors.
        let v = book.vlad(&d).unwrap();
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-5, "norm {norm}");
        assert!(book.vlad(&[]).unwrap().iter().all(|&x| x == 0.0));
    }
}
