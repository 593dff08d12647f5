"""How tests/data/field/seaglider-sg542/ was cut from the shared SG542 files: per dive,
the engineering variables the import reads and the global attributes it and the licence
need, in a netCDF3 file of their own (scipy.io.netcdf_file).

    python tests/data/field/slice_seaglider.py SHARED_DIR tests/data/field/seaglider-sg542
"""

import sys
from pathlib import Path

from scipy.io import netcdf_file

VARIABLES = ("time", "eng_elaps_t", "eng_depth", "eng_pitchAng", "eng_vbdCC", "eng_pitchCtl")
ATTRIBUTES = ("dive_number", "glider", "start_time", "license", "institution", "title")
DIVES = ("p5420304.nc", "p5420305.nc", "p5420306.nc")


def main(source: Path, target: Path) -> None:
    for name in DIVES:
        with (
            netcdf_file(source / name, "r", mmap=False) as src,
            netcdf_file(target / name, "w") as dst,
        ):
            for key in ATTRIBUTES:
                if key in src._attributes:
                    setattr(dst, key, src._attributes[key])
            dst.createDimension("sg_data_point", src.dimensions["sg_data_point"])
            for key in VARIABLES:
                var = src.variables[key]
                out = dst.createVariable(key, "f8", ("sg_data_point",))
                out[:] = var.data
                if hasattr(var, "units"):
                    out.units = var.units


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
