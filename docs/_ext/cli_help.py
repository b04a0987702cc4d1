"""Render the parser's help text in the CLI reference as ``workbench COMMAND --help`` prints it.

sphinx-argparse parses every help string as reStructuredText.  The workbench's parsers are written for the
terminal (``argparse.RawDescriptionHelpFormatter``: descriptions and epilogs are laid out by hand, with
indented example blocks and ``|x|`` norms), so this extension renders a multi-line description or epilog as a
literal block, line for line, and a one-line help string as a plain paragraph (argparse reflows those), never
as markup.  The text keeps its one home, the parser.
"""

import textwrap

import sphinxarg.ext
from docutils import nodes


def render_plain(items, markdown_help, settings=None):
    """sphinx-argparse's ``render_list`` for terminal-formatted help strings (see the module docstring)."""
    out = []
    for element in items:
        if isinstance(element, str):
            text = element.strip("\n")
            if not text.strip():
                continue
            if "\n" in text:
                text = textwrap.dedent(text)
                block = nodes.literal_block(text, text)
                block["language"] = "none"  # plain text: no lexer colours words of the prose
                out.append(block)
            else:
                out.append(nodes.paragraph(text, text))
        elif isinstance(element, nodes.definition):
            out += element
    return out


def setup(app):
    sphinxarg.ext.render_list = render_plain
    return {"parallel_read_safe": True, "parallel_write_safe": True}
