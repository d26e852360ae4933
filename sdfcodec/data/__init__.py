"""Data: synthetic TSDF blocks and scenes, RGB-D sequence readers and renderers, sub-volume sampling."""
