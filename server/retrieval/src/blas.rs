//! One BLAS thread for query-time work.
//!
//! faiss applies a PCA-whitening index's projection with BLAS `sgemm`. OpenBLAS runs even that
//! single-query product on all its threads and then keeps them spinning in `sched_yield` for a
//! while, which on a busy server takes the cores from the feature extractor: on 2 cores, with the
//! projection in every query, extraction went from 10 to 16 ms and the whole query from 50 to 72
//! ms (BENCHMARKS.md, "A deeper shortlist"). One query's projection is a 4096 x 512 product, too
//! small to share, so searches ask OpenBLAS for one thread, once per process. A map built before the
//! process's first search (`pntr build-db`) trains (k-means, PCA) on every thread; one built after
//! it (a test, `pntr eval` without `--db` builds first) trains on one. Another BLAS (reference,
//! BLIS) has no `openblas_set_num_threads` and is left as it is.

#![allow(unsafe_code)] // dlsym and one C call; each use is commented.

use std::sync::Once;

static SINGLE: Once = Once::new();

/// Ask OpenBLAS, when it is the process's BLAS, for a single thread (once; later calls return at
/// once). Returns nothing: without OpenBLAS there is nothing to do.
pub fn single_threaded() {
    SINGLE.call_once(|| {
        // SAFETY: dlsym with RTLD_DEFAULT looks a symbol up among the loaded objects; the name is
        // a NUL-terminated C string literal.
        let f = unsafe { libc::dlsym(libc::RTLD_DEFAULT, c"openblas_set_num_threads".as_ptr()) };
        if f.is_null() {
            return;
        }
        // SAFETY: OpenBLAS declares `void openblas_set_num_threads(int)`; the pointer came from
        // the loader for that very name.
        let set: extern "C" fn(libc::c_int) = unsafe { std::mem::transmute(f) };
        set(1);
    });
}
