"""Missions on a known map (docs/known-map.md): a previous mission's map as the first team,
robots placed in it from wherever they start, lost robots found again, and the map kept up
with a changing building. No I/O here (``server.runtime.mapstore`` reads and writes maps)."""
