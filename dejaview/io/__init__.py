"""MuJoCo interchange: MJCF export and import of scenes (``dejaview.io.mjcf``)."""
