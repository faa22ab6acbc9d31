"""Generated from proto/bgkmap/v1/bgkmap.proto by regen.sh; do not edit."""
