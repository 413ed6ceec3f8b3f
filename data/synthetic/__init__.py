"""Generated scenes: analytic primitives with solid textures (`objects`), an exact ray caster over them (`raycast`).

The `scene` stage's fixture and demo are made from these, and so is any other generator of training data (shape
families, varied layouts): they live here, below the stages, so that more than one stage can use them.
"""
