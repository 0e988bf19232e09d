"""Evidence the Allan curve alone cannot give: spectral lines, temperature sensitivity,
non-stationarity, drift, bias steps and warm-up, outliers and gaps. Each test returns a
:class:`Finding`."""

from analysis.evidence.finding import Finding, family_p
from analysis.evidence.lines import spectral_lines, welch_bins
from analysis.evidence.outliers import gaps, outlier_indices, outliers, robust_z
from analysis.evidence.slow import drift, temperature_correlation
from analysis.evidence.slowgrid import bin_means, slow_grid, slow_regression
from analysis.evidence.stationarity import noise_level_windows
from analysis.evidence.transients import transients

__all__ = ["Finding", "bin_means", "drift", "family_p", "gaps", "noise_level_windows",
           "outlier_indices", "outliers", "robust_z", "slow_grid", "slow_regression",
           "spectral_lines", "temperature_correlation", "transients", "welch_bins"]
