"""Where converted entries and raw messages go: Rerun (``sink``), the layout, the MCAP recorder,
the health series, the progress line, and how far behind the viewer is (``viewer_lag``)."""
