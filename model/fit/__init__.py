"""Right-sizing: the smallest preset of a method family that meets a target, chosen from a ladder of trained sizes.

- ``model.fit.target``: the target (``psnr=``, ``flip=``, ``ms=``, ``within=``) and its parsing;
- ``model.fit.choice``: the ladder's choice from measured numbers, pure (no I/O);
- ``model.fit.plan``: the fit's settings, the checks before any training, the fit key;
- ``model.fit.runner``: timing, obtaining (training or reuse) and measuring presets, registering the choice;
- ``model.fit.report``: the ladder as Markdown and JSON.

How the ladder is built, timed, reused and chosen from: docs/fit.md.
"""
