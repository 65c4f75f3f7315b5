"""Looking at recordings and the live bus: Rerun logging (``rerun_log``), the loopback-only web viewer
(``server``), PNG figures (``figures``, ``frame_figure``) and the shipped sample recording (``sample``)."""
