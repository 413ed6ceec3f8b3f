"""nerfpipe: the repository root is the `nerfpipe` package (pyproject.toml maps it), its folders the subpackages:
`nerfpipe.stages`, `nerfpipe.pipelines`, `nerfpipe.data`, `nerfpipe.radiance`, `nerfpipe.model`, and `nerfpipe.cli`.
Installing puts this one name on the path, not five generic ones (docs/DESIGN.md, "Package names")."""
