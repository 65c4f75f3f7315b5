"""File input/output of fpcore (the only part of fpcore that touches files).

UFF (USTB's HDF5 ultrasound file format) channel data: :func:`read_uff`, :func:`write_uff`.
PICMUS (the IUS 2016 plane-wave challenge's HDF5 files): :func:`read_picmus`, :func:`write_picmus`.
IQ (demodulated) data, in either, are converted to RF on reading: :func:`iq_to_rf`, :func:`rf_to_iq`.
Any of them, or a MATLAB v7.3 file holding either layout: :func:`read_channel_data`.
"""

from fpcore.io.formats import FormatError, detect_format, read_channel_data
from fpcore.io.iq import iq_to_rf, rf_to_iq, rf_upsampling
from fpcore.io.picmus import PICMUSError, read_picmus, write_picmus
from fpcore.io.uff import (
    UFF_VERSION,
    UFFError,
    angles_to_sines,
    list_uff_datasets,
    read_uff,
    read_uff_json,
    sines_to_angles,
    write_uff,
    write_uff_json,
)

__all__ = [
    "FormatError",
    "PICMUSError",
    "UFFError",
    "UFF_VERSION",
    "detect_format",
    "iq_to_rf",
    "read_channel_data",
    "read_picmus",
    "read_uff",
    "rf_to_iq",
    "rf_upsampling",
    "write_picmus",
    "write_uff",
    "list_uff_datasets",
    "read_uff_json",
    "write_uff_json",
    "sines_to_angles",
    "angles_to_sines",
]
