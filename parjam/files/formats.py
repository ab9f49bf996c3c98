"""The names of the file formats parjam reads (``parjam import``) and writes (``parjam export``)
and the extensions that name them: constants only, so that the command line offers them without
loading a file library."""

IMPORT_FORMATS = ("extxyz", "lammps-data", "lammps-dump", "gsd", "h5md")
IMPORT_EXTENSIONS = {".xyz": "extxyz", ".extxyz": "extxyz", ".data": "lammps-data",
                     ".lmp": "lammps-data", ".lammps": "lammps-data", ".dump": "lammps-dump",
                     ".lammpstrj": "lammps-dump", ".gsd": "gsd", ".h5": "h5md", ".h5md": "h5md",
                     ".hdf5": "h5md"}
EXPORT_FORMATS = ("extxyz", "lammps-data", "gsd")
EXPORT_EXTENSIONS = {".xyz": "extxyz", ".extxyz": "extxyz", ".data": "lammps-data",
                     ".lmp": "lammps-data", ".lammps": "lammps-data", ".gsd": "gsd"}
EXPORT_ATOM_STYLES = ("sphere", "atomic")  # LAMMPS data: with diameters, or positions only
