"""Evidence the Allan curve alone cannot give: spectral lines and the power of those the
model holds, temperature sensitivity, non-stationarity, drift, a resonance that moves, bias
steps and warm-up, outliers, held samples and gaps. Each test returns a :class:`Finding`."""

from imunoise.analysis.evidence.finding import Finding, family_p
from imunoise.analysis.evidence.held import held_samples
from imunoise.analysis.evidence.line_power import line_powers
from imunoise.analysis.evidence.lines import line_spectrum, spectral_lines, welch_bins
from imunoise.analysis.evidence.outliers import gaps, outlier_indices, outliers, robust_z
from imunoise.analysis.evidence.resonance_drift import resonance_drift
from imunoise.analysis.evidence.slow import drift, temperature_correlation
from imunoise.analysis.evidence.slowgrid import bin_means, slow_grid, slow_regression
from imunoise.analysis.evidence.stationarity import noise_level_windows
from imunoise.analysis.evidence.transients import transients

__all__ = ["Finding", "bin_means", "drift", "family_p", "gaps", "held_samples",
           "line_powers", "line_spectrum", "noise_level_windows", "outlier_indices", "outliers",
           "resonance_drift", "robust_z", "slow_grid", "slow_regression", "spectral_lines",
           "temperature_correlation",
           "transients", "welch_bins"]
