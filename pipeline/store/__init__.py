"""The HDF5 file: the one writer of its layout, atomic checksummed files, the one reader."""
