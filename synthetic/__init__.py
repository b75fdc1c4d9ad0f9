"""The embedded synthetic glasshouse row: meshes, ray casting, odometry drift, detector noise, writers."""
