import sys

from pipeline._util.interrupts import handle_signals, received

handle_signals()  # before the CLI's imports: an interrupt while they load is one line too
try:
    from pipeline.cli import main  # the console script's entry point: tunes the process
except BaseException:
    if not received():
        raise
    print("error: interrupted while starting; nothing was written", file=sys.stderr)
    sys.exit(128 + received())

sys.exit(main())
