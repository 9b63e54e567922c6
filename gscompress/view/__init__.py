"""The browser viewer of `gsc view` (viser, the optional [view] extra): a log's or a map
file's Gaussians as splats, coloured by RGB, PWAS importance, opacity or what a prune or share
keeps, with live previews of `gsc prune` and `gsc share`, the trajectories, the snapshots and a
second map to compare.

Imported only by `gsc view`; `app` imports viser when a viewer starts.
"""

from gscompress.view.app import MapViewer, ViewOptions

__all__ = ["MapViewer", "ViewOptions"]
