"""Pure numerics on sample arrays: Allan family, PSD, noise terms, fitting, diagnosis.

Nothing here performs I/O or imports :mod:`daq` or :mod:`web`.  All quantities are SI
(rad/s, m/s^2, s, Hz, degC) unless a name says otherwise.
"""
