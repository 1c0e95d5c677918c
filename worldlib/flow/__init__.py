"""Flow routing on a height grid, shared by every stage that needs water to
run downhill: Priority-Flood depression filling and breaching, D8 flow
directions and their tables, D8 accumulation and the wetness index.

`reference` holds the numpy definitions (the D8 tables DR/DC and the cell
kinds live there once); `device` runs the same functions with the kernels in
kernels.cl on the OpenCL device, bit for bit.
"""
