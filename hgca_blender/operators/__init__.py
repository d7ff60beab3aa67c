"""The add-on's operators: import, complete (one region, a whole drive), estimate poses, the georeference origin
and the results, each registered by its module; `watch.JobWatching` is the Esc / status bar part they share."""
