"""Reading and writing: meshes, sensor records, results, images."""
