"""The HDF5 file (docs/hdf5-format.md): ``layout`` names every path and attribute once;
``schema`` (with ``schema_interfaces``) is the one writer of the layout, ``h5file`` writes
atomic, checksummed files and verifies them; ``read`` is the one reader, returning the
typed records of ``records``."""
