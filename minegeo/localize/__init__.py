"""minegeo.localize: georeferencing a map and global localization of scans in it."""
