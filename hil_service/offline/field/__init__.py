"""Field data of real gliders (Seaglider, SeaExplorer, Slocum, any CSV) into our MCAP layout.

``read_field`` turns the vehicle's own files into one ``FieldData`` (SI units, the dives in
order, every irregularity counted); ``grid.resample`` puts the in-dive samples on a uniform
grid, segment by segment; ``write.write_field_log`` writes them as the MCAP log a live
vehicle's service would (docs/field-data.md, docs/mcap.md).
"""

from hil_service.offline.field.detect import FORMATS, read_field
from hil_service.offline.field.table import FieldData, FieldError, Issues

__all__ = ["FORMATS", "FieldData", "FieldError", "Issues", "read_field"]
