"""Files: safe reading and atomic writing, landmark-map formats, maps from above, run folders, LAC
archives."""
