"""Export a trained twin for simulators and viewers (docs/export.md): URDF, MJCF, a GLB per
state and a Gaussian PLY per part, with convex collision pieces, coloured visual meshes,
inertials and joint limits from the observed motion. Entry point: `gear.export.bundle.export_twin`
(this package file stays light: the command line imports `gear.export.defaults` at start-up)."""
