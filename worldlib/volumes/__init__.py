"""Voxel volumes: dense mip levels as EXR slice atlases (`dense`), sparse
column runs of forest sectors (`sparse`), OpenVDB files (`vdb`)."""
