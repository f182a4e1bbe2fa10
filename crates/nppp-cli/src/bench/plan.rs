//! What a bench run measures: the default scenes, the spp ladder and its
//! defaults (`Plan`, from the flags), PT's bounce ladder, and the
//! configurations (`Kind`, `Config`) with their labels as the report and
//! results.csv spell them. Kept apart from the harness so that what is
//! measured can be read (and tested) without how it is run.

use crate::bench_cmd::BenchArgs;
use anyhow::{Result, ensure};
use nppp_render::RenderScene;

/// The M' at which plain path tracing is measured: every M' up to 16, then
/// about two per octave (1, 2, ..., 16, 24, 32, 48, 64, ...) and M itself,
/// so that a translucent scene at M = 256 costs 23 PT configurations, not 256.
pub(super) fn pt_bounce_ladder(m: u32) -> Vec<u32> {
    let mut ladder: Vec<u32> = (1..=m.min(16)).collect();
    // u64: for M near u32::MAX, `step * 2` would wrap to 0 in u32 and the
    // loop would never end (it filled memory).
    let m64 = u64::from(m);
    let mut step = 16u64;
    while step < m64 {
        for x in [step + step / 2, step * 2] {
            if x < m64 {
                ladder.push(x as u32);
            }
        }
        step *= 2;
    }
    if m > 16 {
        ladder.push(m);
    }
    ladder
}

#[cfg(test)]
mod ladder_tests {
    #[test]
    fn ladder_is_every_m_to_16_then_two_per_octave_ending_at_m() {
        assert_eq!(super::pt_bounce_ladder(5), vec![1, 2, 3, 4, 5]);
        let l = super::pt_bounce_ladder(256);
        assert_eq!(&l[15..], &[16, 24, 32, 48, 64, 96, 128, 192, 256]);
        let l = super::pt_bounce_ladder(100);
        assert_eq!(&l[15..], &[16, 24, 32, 48, 64, 96, 100]);
        // Up to u32::MAX: two per octave, ending at M (the doubling once
        // wrapped to 0 and never ended).
        for m in [1u32 << 31, (1 << 31) + 1, u32::MAX] {
            let l = super::pt_bounce_ladder(m);
            assert_eq!(*l.last().unwrap(), m);
            assert!(l.len() < 80, "{} rungs for M = {m}", l.len());
            assert!(l.windows(2).all(|w| w[0] < w[1]));
        }
    }
}

/// The benchmark scenes, in `--scenes-dir`.
pub(super) const DEFAULT_SCENES: &[&str] = &[
    "cornell-box",
    "cornell-glass",
    "cornell-gold",
    "cornell-jade",
    "tube",
    "room",
];
/// Seeds of the reference's two halves: far from the seeds 1..N of the
/// measured renders, whose random streams must not overlap the reference's.
pub(super) const REFERENCE_SEEDS: [u64; 2] = [0x5EED_0000_0001, 0x5EED_0000_0002];
/// Bump when the reference's meaning changes, so old caches are re-rendered.
pub(super) const REFERENCE_FORMAT: u32 = 1;
/// The P values of the thesis' comparison.
pub(super) const NPPP_P: [u32; 4] = [0, 1, 2, 3];

pub(super) struct Plan {
    pub(super) mode: &'static str,
    pub(super) ladder: Vec<u32>,
    pub(super) reference_spp: u32,
    pub(super) seeds: u32,
    pub(super) scale: f64,
}

impl Plan {
    pub(super) fn from_args(a: &BenchArgs) -> Result<Self> {
        let (mode, ladder, reference_spp, seeds, scale) = if a.quick {
            ("quick", vec![4, 16, 64], 512, 2, 0.5)
        } else {
            ("full", vec![4, 16, 64, 256, 1024], 4096, 3, 1.0)
        };
        let mut ladder = a.spp.clone().unwrap_or(ladder);
        ladder.sort_unstable();
        ladder.dedup();
        ensure!(
            !ladder.is_empty() && ladder[0] >= 1,
            "--spp needs at least one value, each at least 1"
        );
        let plan = Plan {
            mode,
            ladder,
            reference_spp: a.reference_spp.unwrap_or(reference_spp),
            seeds: a.seeds.unwrap_or(seeds),
            scale: a.scale.unwrap_or(scale),
        };
        ensure!(
            plan.reference_spp >= 2 && plan.reference_spp.is_multiple_of(2),
            "--reference-spp {}: give an even count of at least 2 (the reference is rendered as \
             two halves of equal spp)",
            plan.reference_spp
        );
        ensure!(
            plan.scale.is_finite() && plan.scale > 0.0 && plan.scale <= 4.0,
            "--scale must be in (0, 4]"
        );
        Ok(plan)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Kind {
    Pt,
    Nppp,
    /// NPPP with next-event estimation through the estimator: at the
    /// picked vertex where every lit estimator has a vertex head, else at
    /// the first vertex (`--entry-nee picked` / `first`).
    NpppNee,
    Oracle,
}

impl Kind {
    /// The `kind` column of results.csv.
    pub(super) fn name(self) -> &'static str {
        match self {
            Kind::Pt => "pt",
            Kind::Nppp => "nppp",
            Kind::NpppNee => "nppp-nee",
            Kind::Oracle => "oracle",
        }
    }

    pub(super) fn from_name(s: &str) -> Option<Self> {
        [Kind::Pt, Kind::Nppp, Kind::NpppNee, Kind::Oracle]
            .into_iter()
            .find(|k| k.name() == s)
    }
}

#[derive(Clone, Debug)]
pub(super) struct Config {
    pub(super) kind: Kind,
    pub(super) m: u32,
    pub(super) p: u32,
}

impl Config {
    pub(super) fn label(&self) -> String {
        match self.kind {
            Kind::Pt => format!("PT M={}", self.m),
            Kind::Nppp => format!("NPPP P={}", self.p),
            Kind::NpppNee => format!("NPPP P={} +NEE", self.p),
            Kind::Oracle => format!("oracle P={}", self.p),
        }
    }
    /// The scene layout this configuration renders: merged for PT,
    /// estimator instances kept apart otherwise (where that differs).
    pub(super) fn scene<'a>(
        &self,
        pt: &'a RenderScene,
        with_estimators: Option<&'a RenderScene>,
    ) -> &'a RenderScene {
        match self.kind {
            Kind::Pt => pt,
            Kind::Nppp | Kind::NpppNee | Kind::Oracle => with_estimators.unwrap_or(pt),
        }
    }
    pub(super) fn slug(&self) -> String {
        match self.kind {
            Kind::Pt => format!("pt-m{}", self.m),
            Kind::Nppp => format!("nppp-p{}", self.p),
            Kind::NpppNee => format!("nppp-nee-p{}", self.p),
            Kind::Oracle => format!("oracle-p{}", self.p),
        }
    }
}
