"""Command-line helpers shared by every entry point of the package (no rclpy import).

Bad arguments or input end in one line `prog: error: <reason>` on stderr and exit status 2
(argparse's convention for usage errors), never in a traceback.
"""
import argparse
import math
import os
import re
import sys


def _prog(module):
    """The name the user typed: the installed executable, or `python -m <module>`."""
    exe = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ''
    if not exe or exe.endswith('.py') or exe.startswith('-'):
        return f'python -m {module}'
    return exe


def one_line(exc):
    """An exception as one readable line: no errno prefix, no C source locations, no line breaks."""
    if isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror + (f': {exc.filename!r}' if exc.filename is not None else '')
    else:
        text = str(exc) or type(exc).__name__
    text = re.sub(r',? at /\S+:\d+', '', text)  # rcl appends the C source location of each error
    return ' '.join(text.split())


class CliParser(argparse.ArgumentParser):
    """argparse for the package's commands: usage errors in one line, help text kept as written.

    module: the dotted module name, for the program name of `python -m` runs.
    """

    def __init__(self, module, **kwargs):
        kwargs.setdefault('prog', _prog(module))
        kwargs.setdefault('formatter_class', argparse.RawDescriptionHelpFormatter)
        super().__init__(**kwargs)

    def error(self, message):
        # argparse would print the whole usage first; one line pointing to --help is easier to read
        self.exit(2, f'{self.prog}: error: {" ".join(message.split())} (see --help)\n')

    def fail(self, exc):
        """Report bad input (an exception) in one line and exit with status 2."""
        self.exit(2, f'{self.prog}: error: {one_line(exc)}\n')


def run_cli(parser, body, argv=None):
    """body(parser.parse_args(argv)); ValueError / OSError (bad input: malformed files, missing
    paths) become `prog: error: <one line>` and exit status 2. Other exceptions, including
    KeyboardInterrupt, pass through: a caller that handles Ctrl-C keeps doing so."""
    args = parser.parse_args(argv)
    try:
        return body(args)
    except (ValueError, OSError) as exc:
        parser.fail(exc)


def number(kind=float, low=None, strict=False, what=None):
    """An argparse type: a finite number (kind float or int) >= low, or > low if strict.

    what: how the refusal describes an accepted value (default e.g. 'a finite number > 0').
    """
    what = what or ('an integer' if kind is int else 'a finite number') + (
        '' if low is None else f' {">" if strict else ">="} {low:g}')

    def convert(text):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not math.isfinite(value) or (
                low is not None and (value <= low if strict else value < low)):
            raise argparse.ArgumentTypeError(f'must be {what}, got {text!r}')
        return value
    return convert


def ros_array(values):
    """A ROS double-array parameter value for `-p name:=...`: repr keeps a decimal point
    ("60.0"), which the parameter parser needs to read a double."""
    return '[' + ','.join(repr(float(v)) for v in values) + ']'
