//! A small typed builder for the report's HTML and SVG: elements with attributes and children,
//! text and attribute values escaped when written. Markup only comes from element names and the
//! page's constant style sheet, never from data.

use std::fmt::Write;

enum Node {
    Text(String),
    /// A constant from this crate (the style sheet), written as it is.
    Static(&'static str),
    El(El),
}

pub struct El {
    tag: &'static str,
    attrs: Vec<(&'static str, String)>,
    children: Vec<Node>,
}

/// An element `tag`.
pub fn el(tag: &'static str) -> El {
    El { tag, attrs: Vec::new(), children: Vec::new() }
}

/// Elements written `<tag ...>` with no children and no end tag in HTML.
const HTML_VOID: [&str; 2] = ["meta", "br"];

impl El {
    pub fn attr(mut self, name: &'static str, value: impl std::fmt::Display) -> Self {
        self.attrs.push((name, value.to_string()));
        self
    }

    /// Text content, escaped.
    pub fn text(mut self, text: impl Into<String>) -> Self {
        self.children.push(Node::Text(text.into()));
        self
    }

    pub fn child(mut self, child: El) -> Self {
        self.children.push(Node::El(child));
        self
    }

    pub fn children(mut self, children: impl IntoIterator<Item = El>) -> Self {
        self.children.extend(children.into_iter().map(Node::El));
        self
    }

    pub(crate) fn static_text(mut self, text: &'static str) -> Self {
        self.children.push(Node::Static(text));
        self
    }

    pub fn write(&self, out: &mut String) {
        out.push('<');
        out.push_str(self.tag);
        for (k, v) in &self.attrs {
            let _ = write!(out, " {k}=\"{}\"", escape(v));
        }
        if HTML_VOID.contains(&self.tag) {
            out.push('>');
            return;
        }
        if self.children.is_empty() && is_svg_shape(self.tag) {
            out.push_str("/>");
            return;
        }
        out.push('>');
        for c in &self.children {
            match c {
                Node::Text(t) => out.push_str(&escape(t)),
                Node::Static(t) => out.push_str(t),
                Node::El(e) => e.write(out),
            }
        }
        let _ = write!(out, "</{}>", self.tag);
    }

    pub fn render(&self) -> String {
        let mut s = String::new();
        self.write(&mut s);
        s
    }
}

fn is_svg_shape(tag: &str) -> bool {
    matches!(tag, "line" | "rect" | "circle" | "polyline" | "path")
}

pub fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// `<p>` with text.
pub fn p(text: impl Into<String>) -> El {
    el("p").text(text)
}

/// A table: a header row, then rows of text cells.
pub fn table<R: IntoIterator<Item = String>>(header: &[&str], rows: impl IntoIterator<Item = R>) -> El {
    let head = el("tr").children(header.iter().map(|h| el("th").text(*h)));
    el("table")
        .child(head)
        .children(rows.into_iter().map(|r| el("tr").children(r.into_iter().map(|c| el("td").text(c)))))
}

/// A figure: content and a caption.
pub fn figure(content: El, caption: impl Into<String>) -> El {
    el("figure").child(content).child(el("figcaption").text(caption))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_and_attributes_are_escaped_and_only_element_names_make_markup() {
        let page = el("div")
            .attr("title", "a \"quoted\" <b>")
            .text("<script>alert(1)</script> & more")
            .child(el("br"))
            .render();
        assert_eq!(
            page,
            "<div title=\"a &quot;quoted&quot; &lt;b&gt;\">&lt;script&gt;alert(1)&lt;/script&gt; &amp; more<br></div>"
        );
        let svg = el("svg").child(el("line").attr("x1", 1.5)).render();
        assert_eq!(svg, "<svg><line x1=\"1.5\"/></svg>");
        let t = table(&["a", "b"], [vec!["1".to_string(), "<2>".to_string()]]).render();
        assert_eq!(t, "<table><tr><th>a</th><th>b</th></tr><tr><td>1</td><td>&lt;2&gt;</td></tr></table>");
    }
}
