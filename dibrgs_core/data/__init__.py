"""Scene input and output: the Scene/View model and splits, LEVIR-NVS, COLMAP, transforms.json and
Metashape layouts, images and depth maps, PLY point clouds."""
