//! FID and KID from two sets of Inception features, as clean-fid computes them
//! (`cleanfid/fid.py`): FID is the Fréchet distance of Gaussians fitted to the sets
//! (`|μ₁ − μ₂|² + tr Σ₁ + tr Σ₂ − 2 tr √(Σ₁Σ₂)`, sample covariances as `np.cov`), KID the
//! unbiased MMD² with the cubic polynomial kernel `k(x, y) = (xᵀy / d + 1)³`, averaged over
//! random subsets (`kernel_distance`: 100 subsets of `min(n₁, n₂, 1000)` by default).
//!
//! `tr √(Σ₁Σ₂)` is computed exactly from the eigenvalues instead of with scipy's `sqrtm`: with
//! fewer samples than dimensions (every small evaluation) it is the nuclear norm of
//! `X₁X₂ᵀ / √((n₁−1)(n₂−1))` for the centred features X, otherwise `Σ √λ(√Σ₁ Σ₂ √Σ₁)`. Where
//! the product is singular scipy's `sqrtm` is itself only approximate, which bounds the
//! agreement of the two.
//!
//! KID's subsets are drawn with a seeded ChaCha generator, not numpy's unseeded global one, so
//! values match clean-fid exactly when a subset is the whole set (every evaluation of at most
//! 1000 frame pairs: each subset is then a permutation of the set, and the estimator does not
//! depend on the order); with larger sets both are estimates of the same expectation, and
//! clean-fid's own value changes from run to run.

use rand::SeedableRng;
use tch::{Kind, Tensor};

use crate::error::{Error, Result};

/// clean-fid's `kernel_distance` defaults.
pub const KID_SUBSETS: usize = 100;
/// clean-fid's `max_subset_size`: subsets hold `min(n₁, n₂, KID_SUBSET_SIZE)` features.
pub const KID_SUBSET_SIZE: usize = 1000;
/// Polynomial degree of KID's kernel (Bińkowski et al. 2018; clean-fid).
const KID_DEGREE: f64 = 3.0;

fn check_features(name: &str, feats: &Tensor, minimum: i64) -> Result<()> {
    let size = feats.size();
    if size.len() != 2 || size[0] < minimum {
        return Err(Error::Shape {
            tensor: name.to_string(),
            expected: format!("[N ≥ {minimum}, D] features"),
            actual: size,
        });
    }
    Ok(())
}

/// FID between feature sets `[n₁, d]` and `[n₂, d]` (each n ≥ 2).
pub fn frechet_distance(feats1: &Tensor, feats2: &Tensor) -> Result<f64> {
    check_features("fid features 1", feats1, 2)?;
    check_features("fid features 2", feats2, 2)?;
    if feats1.size()[1] != feats2.size()[1] {
        return Err(Error::Shape {
            tensor: "fid features 2".to_string(),
            expected: format!("the width of set 1, {:?}", feats1.size()),
            actual: feats2.size(),
        });
    }
    let (x1, x2) = (feats1.to_kind(Kind::Double), feats2.to_kind(Kind::Double));
    let (n1, n2, d) = (x1.size()[0], x2.size()[0], x1.size()[1]);
    let (mu1, mu2) = (x1.mean_dim(0, false, None), x2.mean_dim(0, false, None));
    let (c1, c2) = (&x1 - &mu1, &x2 - &mu2);
    let (s1, s2) = ((n1 - 1) as f64, (n2 - 1) as f64);
    let trace1 = c1.square().sum(Kind::Double).double_value(&[]) / s1;
    let trace2 = c2.square().sum(Kind::Double).double_value(&[]) / s2;
    let tr_covmean = trace_sqrt_product(&c1, &c2, s1, s2, n1 * n2 <= d * d)?;
    let diff = (mu1 - mu2).square().sum(Kind::Double).double_value(&[]);
    Ok(diff + trace1 + trace2 - 2.0 * tr_covmean)
}

/// `tr √(Σ₁Σ₂)` for centred features `c1`, `c2` with covariance divisors `s1`, `s2`: through
/// the `n₁ × n₂` cross-Gram matrix (`gram`) or the `d × d` covariances.
fn trace_sqrt_product(c1: &Tensor, c2: &Tensor, s1: f64, s2: f64, gram: bool) -> Result<f64> {
    if gram {
        // Singular values directly (not √λ(GGᵀ), which turns rounding noise in the zero
        // eigenvalues into √ε-sized terms).
        let g = c1.matmul(&c2.tr()) / (s1 * s2).sqrt();
        let (_, singular, _) = g.f_svd(true, false)?;
        return Ok(singular.sum(Kind::Double).double_value(&[]));
    }
    let sigma1 = c1.tr().matmul(c1) / s1;
    let sigma2 = c2.tr().matmul(c2) / s2;
    let (values, vectors) = sigma1.f_linalg_eigh("L")?;
    let root1 = (&vectors * values.clamp_min(0.0).sqrt().unsqueeze(0)).matmul(&vectors.tr());
    let inner = root1.matmul(&sigma2).matmul(&root1);
    let inner = (&inner + inner.tr()) / 2.0;
    Ok(inner.f_linalg_eigvalsh("L")?.clamp_min(0.0).sqrt().sum(Kind::Double).double_value(&[]))
}

/// The subset size clean-fid's `kernel_distance` uses for sets of `n1` and `n2` features:
/// `min(n1, n2, max_subset_size)`.
pub fn kid_subset_size(n1: usize, n2: usize, max_subset_size: usize) -> usize {
    n1.min(n2).min(max_subset_size)
}

/// KID between feature sets (clean-fid's argument order: `feats1` the first folder) over
/// `subsets` subsets of [`kid_subset_size`] features each.
pub fn kernel_distance(
    feats1: &Tensor,
    feats2: &Tensor,
    subsets: usize,
    max_subset_size: usize,
    seed: u64,
) -> Result<f64> {
    check_features("kid features 1", feats1, 2)?;
    check_features("kid features 2", feats2, 2)?;
    let subset_size = kid_subset_size(feats1.size()[0] as usize, feats2.size()[0] as usize, max_subset_size);
    if subset_size < 2 || subsets == 0 {
        return Err(Error::InvalidArgument {
            name: "kid-subset-size".to_string(),
            reason: format!("{subsets} subsets of {subset_size}: need at least one subset of at least 2"),
        });
    }
    let (f1, f2) = (feats1.to_kind(Kind::Double), feats2.to_kind(Kind::Double));
    let d = f1.size()[1] as f64;
    let m = subset_size as f64;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut pick = |f: &Tensor| {
        let idx: Vec<i64> = rand::seq::index::sample(&mut rng, f.size()[0] as usize, subset_size)
            .into_iter()
            .map(|i| i as i64)
            .collect();
        f.index_select(0, &Tensor::from_slice(&idx))
    };
    let kernel = |a: &Tensor, b: &Tensor| (a.matmul(&b.tr()) / d + 1.0).pow_tensor_scalar(KID_DEGREE);
    let mut total = 0.0;
    for _ in 0..subsets {
        // clean-fid draws from the second set first.
        let x = pick(&f2);
        let y = pick(&f1);
        let a = kernel(&x, &x) + kernel(&y, &y);
        let b = kernel(&x, &y);
        let a_off = a.sum(Kind::Double).double_value(&[]) - a.diagonal(0, 0, 1).sum(Kind::Double).double_value(&[]);
        total += a_off / (m - 1.0) - b.sum(Kind::Double).double_value(&[]) * 2.0 / m;
    }
    Ok(total / subsets as f64 / m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_trace_routes_agree_and_identical_sets_have_zero_fid() {
        let _guard = tch::no_grad_guard();
        tch::manual_seed(0);
        let opts = (Kind::Double, tch::Device::Cpu);
        for (n, d) in [(5, 12), (20, 4)] {
            let a = Tensor::randn([n, d], opts);
            let b = Tensor::randn([n, d], opts) * 2.0 + 1.0;
            let (ca, cb) = (&a - a.mean_dim(0, true, None), &b - b.mean_dim(0, true, None));
            let s = (n - 1) as f64;
            let gram = trace_sqrt_product(&ca, &cb, s, s, true).unwrap();
            let eig = trace_sqrt_product(&ca, &cb, s, s, false).unwrap();
            assert!((gram - eig).abs() < 1e-8 * gram.abs().max(1.0), "n {n} d {d}: {gram} vs {eig}");
            // A rank-deficient covariance leaves √(rounding noise) in the zero eigenvalues.
            let self_fid = frechet_distance(&a, &a).unwrap();
            assert!(self_fid.abs() < 1e-6 * d as f64, "n {n} d {d}: FID(a, a) = {self_fid}");
        }
    }
}
