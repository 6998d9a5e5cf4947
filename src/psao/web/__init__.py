"""The browser client's files as package data: index.html, style.css, the ES modules, shaders/ (GLSL ES)
and vendor/ (the zstd decoder fzstd, a copy of its ESM build, with its LICENSE). psao.server.net.webpage
serves them through importlib.resources; nothing here is Python to import."""
