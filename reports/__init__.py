"""HTML result reports built from pipeline cache manifests."""
