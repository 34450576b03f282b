import sys

from pipeline._util.interrupts import handle_signals, received

handle_signals()  # before the CLI's imports: an interrupt while they load is one line too
try:
    from pipeline.cli.main import main
except BaseException:
    if not received():
        raise
    print("error: interrupted while starting; nothing was written", file=sys.stderr)
    sys.exit(128 + received())

sys.exit(main())
