"""The stages: one package per stage (its declaration, params, algorithms, CLI) and ``stages.common``, their
shared code."""

SHARED_CODE = ("stages.common", "mapformat", "schemas")  # what a stage's code may import besides the engine


def code_digest(stage: str, *also: str) -> str:
    """The digest of a stage's package and of the shared code it imports, through what that imports
    (``pipeline.declare.source_digest``): part of every stage's code_version, so a stage re-runs when any code it
    runs changes, and a committed output is never taken for the output of other code. ``also``: whole packages it
    depends on without importing every module (the published layout)."""
    from pipeline.declare import source_digest

    return source_digest(f"stages.{stage}", *also, follow=SHARED_CODE)


class code_version:  # noqa: N801 - used as a function in the declarations
    """A stage declaration's ``code_version``: ``number`` (raised by hand when a change is meant to re-run the stage)
    and the stage's ``code_digest``, computed when first read (``pipeline.declare.StageDecl``). Picklable."""

    def __init__(self, number: str, stage: str, *also: str):
        self.number, self.stage, self.also = number, stage, also

    def __call__(self) -> str:
        return f"{self.number}+{code_digest(self.stage, *self.also)}"
