//! `nppp bench`'s flags. The benchmark itself (plan, renders, reference
//! cache, analysis, reports and plots) is the module tree `crate::bench`;
//! this file is only the command-line surface, so the text of
//! `nppp bench --help` lives here and nowhere else.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// A few minutes on 2 cores: half resolution, spp 4,16,64, a 512-spp
    /// reference, two seeds. Without it: full resolution, spp 4..1024, a
    /// 4096-spp reference, three seeds (hours on 2 cores).
    #[arg(long)]
    pub quick: bool,
    /// Scenes to run, comma-separated: names in --scenes-dir (without
    /// `.json`) or paths to scene files.
    #[arg(long, value_delimiter = ',')]
    pub scenes: Option<Vec<String>>,
    /// Where scene names are looked up.
    #[arg(long, default_value = "data/scenes")]
    pub scenes_dir: PathBuf,
    /// Output folder: results.md, results.csv, `<scene>.svg/.png`, and per
    /// scene the cached reference and previews.
    #[arg(long, default_value = "out/bench")]
    pub out: PathBuf,
    /// Seeds per measurement (seeds 1..=N); errors are reported as mean and
    /// standard deviation over them.
    #[arg(long, value_parser = crate::at_least_one::<u32>)]
    pub seeds: Option<u32>,
    /// The spp ladder, comma-separated (overrides --quick's and the full default).
    #[arg(long, value_delimiter = ',', value_parser = crate::at_least_one::<u32>)]
    pub spp: Option<Vec<u32>>,
    /// Samples per pixel of the reference (even: rendered as two halves).
    #[arg(long, value_parser = crate::at_least_one::<u32>)]
    pub reference_spp: Option<u32>,
    /// Resolution factor applied to each scene's camera (quick: 0.5, full: 1).
    #[arg(long)]
    pub scale: Option<f64>,
    /// M: the reference's and the NPPP configurations' max bounces; plain
    /// path tracing runs at every M' = 1..M. Default: each scene's own
    /// `render.max_bounces` (cornell-glass renders at M = 10, cornell-jade at
    /// 256, the rest at 5). PT's M' ladder is every value to 16, then about
    /// two per octave.
    #[arg(long, value_parser = crate::at_least_one::<u32>)]
    pub max_bounces: Option<u32>,
    /// Also run PT + oracle (the real object traced alone in place of the
    /// network) at each P: the error the estimator's integration allows.
    #[arg(long)]
    pub oracle: bool,
    /// Re-render the references even if cached ones match.
    #[arg(long)]
    pub fresh_reference: bool,
    /// Render nothing: redraw the time-vs-error plots of an earlier run
    /// from its results.csv into --out (for runs made on a machine without
    /// a TrueType font).
    #[arg(long, value_name = "RESULTS_CSV")]
    pub plot_csv: Option<PathBuf>,
}

/// Runs `nppp bench` (or, with `--plot-csv`, only redraws its plots).
pub fn run(a: &BenchArgs) -> Result<()> {
    crate::bench::run(a)
}
