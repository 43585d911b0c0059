"""Vehicle data: the ReV-StED-schema loader, the drive simulator, datasets and windows.

Torch-free (numpy and the standard library only): the edge runtime's ``prml2 demo``
simulates and encodes drives without the training extra.
"""

from prml2_edge.data.revsted import Drive, load_drive, write_drive_csv

__all__ = ["Drive", "load_drive", "write_drive_csv"]
