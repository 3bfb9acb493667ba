"""Training data: random probe pushes solved by finite elements, stored in ``dataset.zarr``.

``generate_case`` (:mod:`.generate`) runs the protocol of :mod:`biopsynav.probe` on local
worker processes or a Dask cluster; :mod:`.store` holds the Zarr layout. See docs/dataset.md.
"""

from .store import DATASET_NAME, META_FIELDS, open_store, protocol_dict, protocol_fingerprint

__all__ = ["DATASET_NAME", "META_FIELDS", "open_store", "protocol_dict", "protocol_fingerprint"]
