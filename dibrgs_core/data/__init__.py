"""Scene input and output: the Scene/View model and splits, LEVIR-NVS and COLMAP layouts, images and depth maps, PLY point clouds."""
